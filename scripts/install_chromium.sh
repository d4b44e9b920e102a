#!/usr/bin/env bash
# Debian's chromium for the viewer's browser test (tests/test_view.py drives it headless over the
# DevTools protocol; WebGL runs on SwiftShader, no GPU needed). Does nothing when it is there;
# uses sudo when not root.
set -euo pipefail
if [ -x /usr/bin/chromium ] || command -v chromium >/dev/null; then
  exit 0
fi
bash "$(dirname "$0")/apt_install.sh" chromium \
  "install Chromium with your package manager (the viewer's browser test looks for /usr/bin/chromium)"
echo "installed chromium ($(command -v chromium))"
