#!/usr/bin/env bash
# Set up the development environment: system library for open3d, .venv with torch (CPU), the ROS 2 build wheels,
# and this package (editable, with its test extras). Idempotent: `make setup` only calls it when an input changed.
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=.venv
PY=${PYTHON:-python3}

# open3d needs libusb-1.0 (Debian package libusb-1.0-0).
if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
  if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null; then
    echo "setup: installing Debian's libusb-1.0-0 (needed by open3d)"
    (apt-get install -y -q libusb-1.0-0 >/dev/null 2>&1 || { apt-get update -q >/dev/null && apt-get install -y -q libusb-1.0-0 >/dev/null; })
  else
    echo "setup: WARNING: libusb-1.0 is missing and this user cannot install it (apt-get install libusb-1.0-0)" >&2
  fi
fi

# The headless-browser check of the HTML reports (test/report_browser.py) drives Debian's chromium through its
# chromedriver (a browser downloaded by a test tool is not an option here).
if ! command -v chromium >/dev/null || ! command -v chromedriver >/dev/null; then
  if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null; then
    echo "setup: installing Debian's chromium and chromium-driver (the report's browser check)"
    (apt-get update -q >/dev/null && apt-get install -y -q chromium chromium-driver >/dev/null) \
      || echo "setup: WARNING: apt-get could not install chromium chromium-driver: the browser check will skip" >&2
  else
    echo "setup: note: chromium / chromedriver missing and this user cannot install them (apt-get install chromium" \
         "chromium-driver): the browser check of the reports will be skipped" >&2
  fi
fi

if [ ! -x "$VENV/bin/python" ]; then
  echo "setup: creating $VENV"
  "$PY" -m venv "$VENV"
  "$VENV/bin/pip" install -q --upgrade pip
fi
PIP=("$VENV/bin/pip" install -q -c tools/constraints.txt)
# What each step does, as it starts: a first setup takes about 3 minutes, most of it downloads and the msg build.
step() { echo "setup: $* ($(date +%H:%M:%S))"; }
# torch first, from its pinned CPU build, so that no later requirement can pull a CUDA build.
step "torch 2.13.0 (CPU build)"
"${PIP[@]}" torch==2.13.0
# Build requirements of our msg/srv (CMake + rosidl against the ROS 2 wheels), then the package itself without build
# isolation (reuses them: ~15 s instead of ~45 s).
step "build requirements (CMake, rosidl, the ROS 2 wheels)"
"${PIP[@]}" -r tools/build-requirements.txt
step "xmetro_ros and its msg/srv/action interfaces (editable), with the test, train and fleet extras"
"${PIP[@]}" --no-build-isolation -e '.[test,train,fleet]'
"$VENV/bin/python" -c "import xmetro_ros.msg, xmetro_ros.srv, rclpy, open3d, onnxruntime, torch; \
assert torch.version.cuda is None, 'a CUDA build of torch was installed: CPU only'; \
print('setup: ok, torch', torch.__version__)"
