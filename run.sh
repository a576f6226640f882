#!/usr/bin/env bash
# One entry point that sets itself up on a fresh machine (Python >= 3.11), then runs:
#   bash run.sh demo [flags]   the main job on the built-in default scene (see `ne-jax demo --help`)
#   bash run.sh lint           the linter (ruff, configured in pyproject.toml) over the repository
#   bash run.sh test [flags]   the test suite (flags go to pytest; NE_JAX_TEST_WORKERS=2 pytest-xdist
#                              processes, one test file per worker at a time: one XLA:CPU program
#                              does not fill two cores; a crashed worker ends the run instead of
#                              being replaced, since xdist can wait forever on a replacement;
#                              1 runs in-process; each on one host device,
#                              NE_JAX_HOST_DEVICES=1 from tests/conftest.py, programs compiled for
#                              compile speed (XLA's optimisation level 0 and loop emitters, also
#                              conftest.py); the 25 slowest tests
#                              are listed at the end), then, as a second process, the
#                              hard-case suite again in float64 (JAX_ENABLE_X64=1 pytest tests/hard_cases),
#                              the sharding tests on 4 forced host devices (pytest -m multidevice tests/devices),
#                              the viewer in headless Chromium (pytest -m browser tests/view), then the
#                              notebooks in their fast mode (pytest -m notebook tests/notebooks);
#                              with explicit test paths (bash run.sh test tests/foo) only those run
#   bash run.sh <cmd> [flags]  any other `ne-jax` sub-command
# The virtual environment lives in .venv and is re-installed only when pyproject.toml changes.
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
cd "$here"

die() { printf 'run.sh: %s\n' "$*" >&2; exit 1; }

find_python() {
  for py in "${PYTHON:-}" python3.11 python3.12 python3.13 python3; do
    [ -n "$py" ] || continue
    command -v "$py" >/dev/null 2>&1 || continue
    if "$py" -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else 1)' 2>/dev/null; then
      echo "$py"; return 0
    fi
  done
  return 1
}

# Open3D's wheel links against the system library libusb-1.0 and fails to import without it.
ensure_libusb() {
  if ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then return 0; fi
  local sudo=""
  [ "$(id -u)" = 0 ] || { command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null && sudo="sudo -n"; }
  if command -v apt-get >/dev/null 2>&1 && { [ "$(id -u)" = 0 ] || [ -n "$sudo" ]; }; then
    echo "run.sh: installing the system library libusb-1.0 (Debian package libusb-1.0-0) that Open3D needs" >&2
    $sudo apt-get update -qq >/dev/null && DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq libusb-1.0-0 >/dev/null \
      || die "could not install libusb-1.0-0 with apt-get; install it yourself: 'sudo apt-get install libusb-1.0-0'"
    ldconfig 2>/dev/null || true
  else
    die "Open3D needs the system library libusb-1.0, which is missing. Install it, e.g. 'sudo apt-get install libusb-1.0-0' (Debian/Ubuntu), 'sudo dnf install libusb1' (Fedora), 'brew install libusb' (macOS), then run this again."
  fi
}

setup() {
  ensure_libusb
  local py; py="$(find_python)" || die "Python >= 3.11 not found (tried python3.11, python3.12, python3.13, python3); set PYTHON=/path/to/python3.11"
  if [ ! -x .venv/bin/python ]; then
    echo "run.sh: creating .venv with $("$py" --version)" >&2
    "$py" -m venv .venv
  fi
  # An NVIDIA GPU (nvidia-smi runs and finds one) adds JAX's CUDA 12 plugin (the cuda12 extra); the stamp
  # names the extras, so a machine that gains or loses a GPU installs again.
  local stamp=".venv/.ne_jax_installed" want extras="test"
  if command -v nvidia-smi >/dev/null 2>&1 && nvidia-smi -L >/dev/null 2>&1; then extras="test,cuda12"; fi
  want="$(sha256sum pyproject.toml | cut -d' ' -f1) $extras"
  if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
    echo "run.sh: installing ne_jax and its dependencies into .venv, extras $extras (first run: a few minutes)" >&2
    .venv/bin/python -m pip install -q --upgrade pip
    .venv/bin/python -m pip install -q -e ".[$extras]"
    echo "$want" > "$stamp"
  fi
}

cmd="${1:-}"
[ -n "$cmd" ] || die "usage: bash run.sh demo|test|<ne-jax sub-command> [flags]"
shift
setup
# Huge pages for XLA:CPU's per-call scratch memory (25x fewer page faults per step; ne_jax/_host_memory.py),
# unless NE_JAX_HOST_MEMORY=system or GLIBC_TUNABLES already sets it (glibc ignores it elsewhere).
if [ "${NE_JAX_HOST_MEMORY:-}" != system ] && [[ "${GLIBC_TUNABLES:-}" != *glibc.malloc.hugetlb* ]]; then
  export GLIBC_TUNABLES="${GLIBC_TUNABLES:+$GLIBC_TUNABLES:}glibc.malloc.hugetlb=1"
fi
case "$cmd" in
  lint) exec .venv/bin/ruff check . ;;
  test)
    # Explicit paths (an argument naming a file or folder, optionally with ::test): run just those.
    for arg in "$@"; do
      case "$arg" in -*) continue ;; esac
      if [ -e "${arg%%::*}" ]; then exec .venv/bin/python -m pytest "$@"; fi
    done
    workers="${NE_JAX_TEST_WORKERS:-2}"
    xdist=()
    if [ "$workers" -gt 1 ]; then xdist=(-n "$workers" --dist loadfile --max-worker-restart 0); fi
    .venv/bin/python -m pytest "${xdist[@]}" --durations=25 "$@"
    echo "run.sh: float64 step: JAX_ENABLE_X64=1 pytest tests/hard_cases" >&2
    JAX_ENABLE_X64=1 .venv/bin/python -m pytest tests/hard_cases -q
    echo "run.sh: multi-device step: 4 forced host devices, pytest -m multidevice tests/devices" >&2
    XLA_FLAGS="${XLA_FLAGS:-} --xla_force_host_platform_device_count=4" .venv/bin/python -m pytest tests/devices -m multidevice -q
    echo "run.sh: browser step: pytest -m browser tests/view (headless Chromium; skipped without chromium and chromedriver)" >&2
    .venv/bin/python -m pytest tests/view -m browser -q
    echo "run.sh: notebook step: pytest -m notebook tests/notebooks (each notebook in its fast mode)" >&2
    exec .venv/bin/python -m pytest tests/notebooks -m notebook -q ;;
  *)    exec .venv/bin/ne-jax "$cmd" "$@" ;;
esac
