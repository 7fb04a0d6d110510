#!/usr/bin/env bash
# Set up usdrelight on a fresh Debian/Ubuntu machine: system LLVM for drjit, a virtual
# environment in .venv with the package (editable) and its test extras.
# Idempotent: a second run only re-installs when pyproject.toml changed.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
EXTRAS=${USDRELIGHT_EXTRAS:-test,estimate}
# torch for the estimate extra, installed before it: this pinned CPU build (found as a local wheel on the
# project's machines) keeps pip from resolving the extra's plain `torch` to the multi-GB CUDA build
TORCH_PIN=${USDRELIGHT_TORCH:-torch==2.13.0}

log() { printf 'setup: %s\n' "$*" >&2; }

# drjit's LLVM backend (mitsuba's llvm_ad_rgb) needs libLLVM >= 16; Debian's default 14/15 crash it
# ("Cannot select fminimum"). Install Debian's libllvm19 when no suitable libLLVM is present.
have_llvm() {
  local f
  for f in /usr/lib/*/libLLVM.so.1[6-9]* /usr/lib/*/libLLVM-1[6-9].so* /usr/lib/*/libLLVM.so.2[0-9]* \
           /usr/lib/*/libLLVM-2[0-9].so* /usr/lib/llvm-1[6-9]/lib/libLLVM*.so* /usr/lib/llvm-2[0-9]/lib/libLLVM*.so*; do
    [ -e "$f" ] && return 0
  done
  return 1
}
if ! have_llvm; then
  SUDO=""; [ "$(id -u)" -ne 0 ] && command -v sudo >/dev/null && SUDO="sudo"
  if command -v apt-get >/dev/null; then
    log "installing libllvm19 (drjit LLVM backend)"
    $SUDO apt-get install -y -qq libllvm19 >/dev/null 2>&1 || { $SUDO apt-get update -qq && $SUDO apt-get install -y -qq libllvm19 >/dev/null; }
  else
    log "WARNING: no apt-get; install LLVM >= 16 yourself and set DRJIT_LIBLLVM_PATH"
  fi
fi

# The web app's browser test (tests/test_serve.py) drives Debian's Chromium with Playwright (Playwright's own
# browser download is not used). Optional: when it cannot be installed, that test is skipped with the reason.
if [ ! -x /usr/bin/chromium ] && [ "${USDRELIGHT_SKIP_CHROMIUM:-0}" != "1" ]; then
  SUDO=""; [ "$(id -u)" -ne 0 ] && command -v sudo >/dev/null && SUDO="sudo"
  if command -v apt-get >/dev/null; then
    log "installing chromium (browser test of usdrelight serve)"
    $SUDO apt-get install -y -qq chromium >/dev/null 2>&1 || { $SUDO apt-get update -qq >/dev/null 2>&1 && \
      $SUDO apt-get install -y -qq chromium >/dev/null 2>&1; } || \
      log "WARNING: chromium not installed: the browser test of usdrelight serve will be skipped"
  else
    log "WARNING: no apt-get; without /usr/bin/chromium the browser test of usdrelight serve is skipped"
  fi
fi

if [ ! -x .venv/bin/python ]; then
  log "creating .venv"
  "$PY" -m venv .venv
fi
stamp=.venv/.usdrelight-installed
want="$(cat pyproject.toml | sha256sum | cut -d' ' -f1)-$EXTRAS"
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ] || ! .venv/bin/python -c 'import usdrelight' 2>/dev/null; then
  log "installing usdrelight[$EXTRAS] into .venv"
  .venv/bin/python -m pip install -q --upgrade pip >/dev/null
  case ",$EXTRAS," in
    *,estimate,*|*,train,*)
      if ! .venv/bin/python -c 'import torch' 2>/dev/null; then
        log "installing $TORCH_PIN (the estimate extra's torch, before the extra)"
        .venv/bin/python -m pip install -q "$TORCH_PIN"
      fi ;;
  esac
  .venv/bin/python -m pip install -q -e ".[$EXTRAS]"
  echo "$want" > "$stamp"
fi
# Blender as a Python module (bpy 5.0.1, CPython 3.11 only, pins numpy<2) lives in its own environment;
# usdrelight runs it in a subprocess (converters/blender.py). USDRELIGHT_SKIP_BLENDER=1 skips it.
if [ "${USDRELIGHT_SKIP_BLENDER:-0}" != "1" ] && [ ! -f .venv-blender/.bpy-installed ]; then
  PY311=""
  for cand in python3.11 "$PY"; do
    if command -v "$cand" >/dev/null && "$cand" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))'; then
      PY311=$(command -v "$cand"); break
    fi
  done
  if [ -z "$PY311" ]; then
    log "ERROR: bpy==5.0.1 needs CPython 3.11 (python3.11 not found); set USDRELIGHT_SKIP_BLENDER=1 to skip Blender"
    exit 1
  fi
  log "installing bpy==5.0.1 into .venv-blender (Blender as a Python module, ~1 GB)"
  [ -x .venv-blender/bin/python ] || "$PY311" -m venv .venv-blender
  .venv-blender/bin/python -m pip install -q --upgrade pip >/dev/null
  .venv-blender/bin/python -m pip install -q "bpy==5.0.1"
  touch .venv-blender/.bpy-installed
fi
log "ready: $(.venv/bin/python -c 'import usdrelight, sys; print("usdrelight", usdrelight.__version__, "on python", sys.version.split()[0])')"
