"""Save in the web app: ``lights_user.usda`` gets the lights the app changed, and no other opinion changes.

* Only a light added, removed, edited or re-keyed since the app read the file (or saved it last) is rewritten
  (:func:`changed_names`): a light the user never touched keeps its spec as written, its default values and its
  transform ops. A Save with nothing changed (and the range as it was) writes nothing; a Save that writes
  re-exports the file as USD writes it (comments and number formatting are not kept).
* A keyed light changed at a frame without "Set key" is refused (:func:`unkeyed_changes`): Save writes a keyed
  light from its keys, so the change would be lost while the status said saved.
* Each light rewritten must still be in the file as the app read it (:func:`.opinions.spec_texts`): another app
  on the same stage, or a tool, that saved it meanwhile is not overwritten (one error line naming it).
* Temporary files of a save that was killed (``.lights_user.usdrelight-tmp-XXXXXXXX.usda``) are removed while
  the stage's lock is held; the file is replaced atomically, only it.
"""
from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import time
from pathlib import Path

from ..atomic import LOCK_NAME, is_temp_file_of, stage_lock, write_text_atomic
from ..errors import UsdRelightError
from ..stage.layout import USER_LIGHTS, USER_LIGHTS_SCOPE
from .files import user_layer_names, user_layer_text
from .opinions import spec_texts

log = logging.getLogger(__name__)
SAVE_WAIT = 10.0
"""Seconds a Save waits for another process that writes the stage (a fit, a relight --save-lights)."""


@contextlib.contextmanager
def _locked(folder: Path, wait: float):
    """:func:`usdrelight.atomic.stage_lock` of ``folder``, retried for up to ``wait`` seconds while another
    writer (a process, or another thread of this one) holds it."""
    end, misses = time.monotonic() + wait, 0
    with contextlib.ExitStack() as stack:
        while True:
            try:
                stack.enter_context(stage_lock(folder))
                break
            except UsdRelightError:
                if time.monotonic() >= end:
                    raise
                if not (folder / LOCK_NAME).exists():  # released meanwhile, or not a lock at all (permissions)
                    misses += 1
                    if misses > 3:
                        raise
                    continue
                misses = 0
            time.sleep(0.05)
        yield


def write_user_layer(stage_dir, states, managed=(), hdri_paths: dict | None = None, wait: float = 0.0,
                     keys: dict | None = None, timing: dict | None = None, expected: dict | None = None,
                     specs: dict | None = None) -> Path:
    """Replace ``STAGE_DIR/lights_user.usda`` atomically (see :func:`.files.user_layer_text`); only that file.
    The stage lock is taken first (every stage writer holds it), waiting up to ``wait`` seconds for another
    writer ("stage ... is being written by PID N" after that). ``specs`` (a dict) gains the spec texts of the
    ``managed`` lights as written, read under the lock (what the next Save expects to find)."""
    target = Path(stage_dir).resolve() / USER_LIGHTS
    from pxr import Sdf

    with _locked(target.parent, wait):  # read, edit and replace under the lock: no other writer's change is lost
        for p in target.parent.glob(".*.usda"):  # what a killed save left (only this file's temporaries)
            if is_temp_file_of(p, USER_LIGHTS) and p.is_file() and not p.is_symlink():
                p.unlink(missing_ok=True)
        text = user_layer_text(stage_dir, states, managed, hdri_paths, keys, timing, expected)
        write_text_atomic(target, text)
        if specs is not None:
            written = Sdf.Layer.CreateAnonymous(".usda")
            written.ImportFromString(text)
            specs.update(spec_texts(written, USER_LIGHTS_SCOPE, managed))
        cached = Sdf.Layer.Find(str(target))
        if cached is not None:  # a stage open in this process sees the new file
            cached.Reload(force=True)
    log.info("saved %d light(s) to %s", len(states), target)
    return target


def changed_names(states: dict, keys: dict, managed: set, baseline: dict) -> set[str]:
    """The lights to rewrite: ``states`` ({name: LightState} now) and ``keys`` ({name: {time: state}}) against
    ``baseline`` ({name: (state, keys or None)} as read or last saved): new ones, removed ones (in ``managed``,
    no longer in ``states``, that the file held), and those whose keys (a keyed light) or state changed."""
    out = set()
    for name in set(managed) | set(states):
        base = baseline.get(name)
        if name not in states:
            if base is not None:
                out.add(name)
        elif base is None or (keys.get(name) or None) != (base[1] or None) or \
                (not keys.get(name) and states[name] != base[0]):
            out.add(name)
    return out


def unkeyed_changes(states: dict, timeline) -> list[str]:
    """Keyed lights whose state at the timeline's frame is not what their keys give there (changed without "Set
    key"): sorted names."""
    out = []
    for name, s in states.items():
        if timeline.keys.get(name) and not _same(timeline.state_at(name, timeline.frame), s):
            out.append(name)
    return sorted(out)


def _same(a, b) -> bool:
    """Two light states equal up to float32 rounding (a key read back through USD against the one set)."""
    def close(x, y):
        if isinstance(x, (tuple, list)) and isinstance(y, (tuple, list)):
            return len(x) == len(y) and all(close(p, q) for p, q in zip(x, y))
        if isinstance(x, (int, float)) and isinstance(y, (int, float)) and not isinstance(x, bool):
            return math.isclose(x, y, rel_tol=1e-6, abs_tol=1e-7)
        return x == y
    return close(dataclasses.astuple(a), dataclasses.astuple(b))


def baseline_of(states, keys: dict) -> dict:
    """{name: (state, keys or None)} of the lights as read (``states``: a keyed light's first key)."""
    return {s.name: (s, dict(keys[s.name]) if keys.get(s.name) else None) for s in states}


def save_lights(owner, lock) -> Path:
    """``owner``'s Save (a :class:`.app.ServeApp`, its state read and updated holding ``lock``; see the module
    docstring). The caller runs one Save at a time."""
    with lock:
        states, managed, keys = dict(owner.states), set(owner.managed), owner.timeline.snapshot()
        unkeyed, frame = unkeyed_changes(states, owner.timeline), owner.timeline.frame
    if unkeyed:
        raise UsdRelightError(f"{', '.join(unkeyed)} changed at frame {frame:g} without a key: Set key (or go to "
                              "another frame to drop the change), then Save")
    if clash := (set(states) - managed) & user_layer_names(owner.stage_dir):  # a user's, meanwhile
        raise UsdRelightError(f"lights_user.usda gained {', '.join(sorted(clash))} while the app ran: rename")
    changed, timing = changed_names(states, keys, managed, owner.baseline), owner.timeline.timing()
    if not changed and not (timing and timing.get("edited")):  # nothing to write: the file stays as it is
        return Path(owner.stage_dir).resolve() / USER_LIGHTS
    written: dict = {}
    path = write_user_layer(owner.stage_dir, [states[n] for n in sorted(changed) if n in states], changed,
                            owner.hdris, wait=SAVE_WAIT, keys={n: keys[n] for n in changed if n in keys},
                            timing=timing, expected={n: owner.on_disk.get(n) for n in changed}, specs=written)
    with lock:
        owner.managed = managed | set(states)
        for name in changed:
            if name in states:
                owner.baseline[name] = (states[name], keys.get(name))
            else:
                owner.baseline.pop(name, None)
        owner.on_disk.update(written)  # read under the stage's lock: another app's save after it is seen
    return path
