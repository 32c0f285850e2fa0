#!/usr/bin/env bash
# Make headless Chromium available for the dashboard's browser test (tests/test_dashboard.py); run by
# `make setup`, idempotent and quick when it is already there.
#
# * Nothing to do when a Chromium is on PATH (chromium, chromium-browser, google-chrome; or $HAA_CHROMIUM).
# * Else installs Debian's `chromium` package with apt-get (as root, or through sudo), running
#   `apt-get update` first.
# * Never fails `make setup`: without root, without apt-get, with HAA_SKIP_APT=1 or when the install fails it
#   says so and goes on — the browser test then skips with the reason (HAA_REQUIRE_BROWSER=1, as in CI, makes
#   it fail instead).
set -uo pipefail

say() { echo "browser-setup: $*"; }
have() { command -v "$1" >/dev/null 2>&1; }

for b in "${HAA_CHROMIUM:-}" chromium chromium-browser google-chrome google-chrome-stable; do
    if [ -n "$b" ] && have "$b"; then
        exit 0
    fi
done
if [ "${HAA_SKIP_APT:-}" = 1 ]; then
    say "no Chromium and HAA_SKIP_APT=1: the dashboard's browser test will be skipped"
    exit 0
fi
if ! have apt-get; then
    say "no Chromium and no apt-get: install Chromium yourself, or the dashboard's browser test is skipped"
    exit 0
fi
SUDO=()
if [ "$(id -u)" != 0 ]; then
    if have sudo; then
        SUDO=(sudo)
    else
        say "no Chromium, and installing Debian's chromium needs root: the dashboard's browser test will be skipped"
        exit 0
    fi
fi
say "installing Debian's chromium (apt-get)"
export DEBIAN_FRONTEND=noninteractive
if "${SUDO[@]}" apt-get update -qq && "${SUDO[@]}" apt-get install -y -qq --no-install-recommends chromium >/dev/null; then
    say "installed $(chromium --version 2>/dev/null || echo chromium)"
else
    say "warning: apt-get could not install chromium: the dashboard's browser test will be skipped" >&2
fi
exit 0
