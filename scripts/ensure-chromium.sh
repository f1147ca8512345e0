#!/usr/bin/env bash
# The report test opens the HTML in headless Chromium (Debian's package); install it if
# it is missing and we are allowed to.
set -euo pipefail
command -v chromium >/dev/null 2>&1 && exit 0
SUDO=""
[ "$(id -u)" = 0 ] || SUDO="sudo"
if command -v apt-get >/dev/null 2>&1; then
  echo "installing chromium for the report test (apt-get) ..."
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq chromium >/dev/null
else
  echo "warning: no chromium and no apt-get; the report browser test will fail" >&2
fi
