"""Outputs no file can be made at, and options a mode cannot honour: one line before the work (exit 2), never
an 'unexpected' OS error after it."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from conftest import build_procedural
from usdrelight.stage.lights_layer import write_fitted_lights
from usdrelight.stage.records import FitProvenance, PointLightValue


def _one_line(rc, err, needle):
    assert rc == 2 and err.count("\n") == 1 and err.startswith("usdrelight: error:"), (rc, err)
    assert "unexpected" not in err and needle in err, err


def test_train_checks_its_model_path_before_training(cli, tmp_path):
    """-o m.txt, a folder, a path under a file, /proc: 'unexpected FileExistsError/IsADirectoryError/
    FileNotFoundError' with exit 1, after the whole training."""
    (tmp_path / "afile").write_text("")
    for out, needle in ((tmp_path / "m.txt", "the model is an .onnx file"),
                        (tmp_path, "the model is an .onnx file"),
                        (tmp_path / "afile" / "m.onnx", "is not a folder"),
                        (Path("/proc/m.onnx"), "cannot write /proc/m_work")):
        rc, _, err = cli("train", tmp_path / "no_pairs_here", "-o", out, "--steps", "1")
        _one_line(rc, err, needle)


def test_a_video_where_no_file_can_be_made_and_add_with_a_dimmer(cli, tmp_path, caplog):
    stage = build_procedural(tmp_path / "st", stride=4)
    write_fitted_lights(tmp_path / "st", [PointLightValue(np.array([0.5, 1.0, -1.5]), np.array([3.0, 3.0, 3.0]))],
                        None, FitProvenance("fast", 0.0, 0.0, 0.0, 0))
    rc, _, err = cli("relight", stage, "--light", "point:0,1,-2:2,2,2", "--frames", "1:2", "--video",
                     "/proc/x.mp4", "-o", tmp_path / "v")
    _one_line(rc, err, "cannot write /proc/x.mp4")
    assert not (tmp_path / "v").exists()
    # add keeps the photo as it is: a dimmer cannot apply there (it gave daylight, bit for bit, in silence)
    rc, _, err = cli("relight", stage, "--mode", "add", "--fitted-scale", "0.05", "--max-side", "32", "-o",
                     tmp_path / "a")
    assert rc == 0 and "--mode add keeps the photo's own light as it is: --fitted-scale 0.05 is not applied" in err
