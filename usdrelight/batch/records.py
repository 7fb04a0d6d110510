"""Records handed between the batch steps: options (client), a photo's job (client -> worker), a manifest
row (worker -> client -> ``manifest.jsonl``) and the run's summary (``--json``)."""
from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

MANIFEST_FIELDS_VERSION = 1
"""Bumped when the manifest's meaning changes (part of every input hash)."""
REFUSED = "refused"
"""Manifest status of a file of the photo folder that is not processed (its ``error`` says why: a control
character in its name, a symbolic link out of the folder ...); every run lists them again."""


@dataclass(frozen=True)
class BatchOptions:
    """What ``usdrelight batch`` does to each photo; every field except the scheduling ones is hashed."""

    max_side: int = 512
    """Longer image side of the light fit, pixels."""
    lights: int = 16
    """Most point lights the fit may keep (K)."""
    iterations: int = 40
    """Position iterations of the fast fit."""
    verify_spp: int = 0
    """Samples per pixel of the fit's Mitsuba verification render; 0 = no verification render."""
    pairs: bool = False
    """Also render the training pair (D~, albedo, valid) into ``NAME/renders``."""
    spp: int = 64
    """Samples per pixel of the pair's D~ render."""
    workers: int | None = None
    """LocalCluster worker processes (1 thread each); None: 2, or fewer on a machine with fewer cores or
    too little memory (:func:`usdrelight.batch.guard.resolve_workers`); not hashed."""
    scheduler: str | None = None
    """Address of an existing Dask scheduler (``tcp://host:8786``) instead of a LocalCluster; not hashed."""
    retries: int = 2
    """A photo whose worker dies is tried again this many times before it is recorded failed; not hashed."""
    retry_failed: bool = False
    """Redo photos recorded failed on an input error even when their inputs are unchanged; not hashed."""
    dashboard: bool = True
    """Start the LocalCluster's dashboard (a random free port on 127.0.0.1); not hashed."""
    geometry: str | None = None
    """``--geometry``: the geometry estimator of photos without a depth or point-map sidecar."""
    albedo_from: str | None = None
    """``--albedo-from``: the decomposition of photos without an albedo sidecar."""
    model_paths: tuple = ()
    """Local model snapshots (``--model-path``, plus the cache folders the client found): hashed."""
    device: str | None = None
    """Torch device of the learned estimators (auto when None); not hashed."""
    model_digests: tuple = ()
    """sha256 (hex) of each ``onnx:FILE`` model named by ``geometry`` and ``albedo_from``: hashed."""

    def hashed(self) -> dict:
        """The options that change a photo's outputs (the rest only schedule the work). The estimator options
        are hashed only when given, so the hashes of batches made without them stay as they were."""
        out = {"max_side": self.max_side, "lights": self.lights, "iterations": self.iterations,
               "verify_spp": self.verify_spp, "pairs": self.pairs, "spp": self.spp if self.pairs else None}
        if self.geometry or self.albedo_from:
            out.update(geometry=self.geometry, albedo_from=self.albedo_from,
                       model_paths=[str(p) for p in self.model_paths])
        if self.model_digests:  # apart, so the hashes of batches without ONNX models stay as they were
            out.update(model_digests=list(self.model_digests))
        return out

    def estimators(self) -> dict:
        """The build options of the learned estimators (:func:`usdrelight.neural.pairs.build_options`)."""
        return {"geometry": self.geometry, "albedo_from": self.albedo_from, "model_paths": tuple(self.model_paths),
                "device": self.device}


@dataclass(frozen=True)
class PhotoJob:
    """One photo to process, as sent to a worker."""

    name: str
    """The photo's file stem: its output folder is ``out_dir/name``."""
    photo: Path
    """The photo file (absolute)."""
    inputs: tuple
    """The photo and its sidecar files (absolute paths), as hashed."""
    input_hash: str
    """sha256 (hex) over the inputs' names and bytes, the hashed options and the manifest version."""
    out_dir: Path
    """The batch output folder (absolute)."""
    options: BatchOptions
    """The batch's options."""
    lock_token: str = ""
    """:func:`usdrelight.atomic.lock_token` of ``out_dir`` while the batch that sent the job holds it: a worker
    publishes the photo only while it is still the same (an external worker finishing after its batch ended, or
    was interrupted, writes nothing); "" = no check."""


@dataclass
class PhotoRecord:
    """One line of ``manifest.jsonl`` (also ``out_dir/NAME/batch.json`` for a finished photo)."""

    name: str
    """The photo's file stem (its folder in the output); a refused file's whole name."""
    status: str
    """done | failed | refused (not processed, see :data:`REFUSED`)."""
    input_hash: str
    """:attr:`PhotoJob.input_hash` of the run that made this record."""
    photo: str
    """The photo file (absolute path)."""
    error: str | None = None
    """One line: why it failed or was refused (None when done)."""
    error_kind: str | None = None
    """input (a usdrelight error: bad file, no valid depth, fit error; not retried while the inputs are
    unchanged) | crash (the worker died or an unexpected exception; retried on the next run); None when
    done or refused."""
    fit_mse: float | None = None
    """Masked MSE of the fit's model against D (linear RGB)."""
    fit_psnr_db: float | None = None
    """PSNR of ``fit_mse`` (peak = max of D), dB."""
    fit_mse_rel: float | None = None
    """``fit_mse`` over the photo's mean squared value on valid pixels (with ``--pairs``): the paper's
    worst-fit filter ranks by this."""
    render_psnr_db: float | None = None
    """PSNR of the Mitsuba verification render, dB (None without ``--verify-spp``)."""
    fit_seconds: float | None = None
    """Wall time of the light fit's optimisation, s."""
    build_seconds: float | None = None
    """Wall time of ``build``, s."""
    render_seconds: float | None = None
    """Wall time of the pair's renders, s (0 without ``--pairs``)."""
    seconds: float | None = None
    """Wall time of the whole photo on its worker (build, fit, renders, publishing), s."""
    lights_kept: int | None = None
    """Point lights in the fitted-lights layer."""
    environment_kept: bool | None = None
    """Whether the fitted environment was kept."""
    pairs: bool = False
    """The training pair was rendered (``NAME/renders``, ``NAME/pair.json``)."""
    worker: str | None = None
    """Address of the worker that made the record (None for a crash recorded by the client)."""

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "PhotoRecord":
        names = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in names})


@dataclass
class BatchSummary:
    """What a batch run did (``--json``)."""

    out_dir: str
    """The output folder."""
    manifest: str
    """Path of ``manifest.jsonl``."""
    photos: int
    """Photos in the input folder that can be processed (refused files not counted)."""
    done: int
    """Photos processed in this run that ended done."""
    failed: int
    """Photos processed in this run that ended failed."""
    skipped: int
    """Photos not processed: inputs and options unchanged and outputs complete (or an unchanged input
    failure, without ``--retry-failed``)."""
    manifest_done: int
    """Rows of the manifest with status done after the run."""
    manifest_failed: int
    """Rows of the manifest with status failed after the run."""
    seconds: float
    """Wall time of the whole run, s (cluster start included)."""
    cluster_seconds: float
    """Wall time to start (or connect to) the Dask cluster, s; 0 when nothing had to run."""
    scheduler: str | None
    """The scheduler's address (None when nothing had to run)."""
    dashboard: str | None
    """The Dask dashboard's address, when there is one."""
    workers: int
    """Workers the cluster had when the run started."""
    refused: int = 0
    """Files of the photo folder not processed (listed in ``per_photo`` and the manifest with their reason)."""
    orphaned: list = field(default_factory=list)
    """Names of output folders an earlier run made for photos no longer in the photo folder: kept as they are,
    no longer in the manifest (delete them yourself)."""
    per_photo: list = field(default_factory=list)
    """[{name, outcome (done | failed | skipped | refused), seconds, build_seconds, fit_seconds, fit_psnr_db,
    error}]; a refused file's error says why."""

    def to_dict(self) -> dict:
        return asdict(self)
