#!/usr/bin/env bash
# apt_install.sh PACKAGE HINT: apt-installs Debian's PACKAGE (sudo when not root); without apt-get,
# prints HINT (how to install it otherwise) and fails. The install_*.sh scripts call it.
set -euo pipefail
package="$1"
hint="$2"
if ! command -v apt-get >/dev/null; then
  echo "$hint" >&2
  exit 1
fi
sudo=""
[ "$(id -u)" -eq 0 ] || sudo="sudo"
$sudo apt-get update -qq
$sudo apt-get install -y -qq "$package" >/dev/null
