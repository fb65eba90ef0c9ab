#!/usr/bin/env bash
# Makes sure headless Chromium is installed (once) and prints its path.
#
#   scripts/chromium.sh              -> last line of stdout: /abs/path/to/chromium
#
# Used by the report test (tests/tests/report_html.rs), which renders the lab's HTML reports.
# If `chromium` (or $CHROMIUM) is already on PATH nothing is installed, so after the first run
# this works offline. Otherwise, on Debian/Ubuntu, the `chromium` package is installed with
# apt-get (needs root, or passwordless sudo). Everything but the final path goes to stderr.
#
# Start it with at least:
#   --headless --no-sandbox --disable-gpu --disable-quic --no-first-run
#   --disable-background-networking --disable-component-update --disable-sync
#   --user-data-dir=<fresh temp dir>
# (without the networking flags it waits on the network when there is none).
set -euo pipefail

die() {
    echo "chromium.sh: error: $*" >&2
    exit 1
}

find_chromium() {
    local c
    for c in ${CHROMIUM:-} chromium chromium-browser; do
        if command -v "$c" >/dev/null 2>&1; then
            command -v "$c"
            return 0
        fi
    done
    return 1
}

if path="$(find_chromium)"; then
    echo "$path"
    exit 0
fi

command -v apt-get >/dev/null 2>&1 ||
    die "chromium is not installed and there is no apt-get: install Chromium (binary 'chromium' on PATH) or set CHROMIUM"

sudo=()
if [ "$(id -u)" != 0 ]; then
    command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null ||
        die "chromium is not installed and installing it needs root: run 'apt-get install chromium' as root"
    sudo=(sudo -n)
fi

# Serialize concurrent callers (several test binaries may ask at once); apt has its own lock
# but fails rather than waits.
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
lock="${TMPDIR:-/tmp}/scancorr-chromium.lock"
if command -v flock >/dev/null 2>&1; then
    exec 9>"$lock"
    flock -w 1200 9 || die "timed out waiting for $lock"
    # Someone else may have installed it while we waited.
    if path="$(find_chromium)"; then
        echo "$path"
        exit 0
    fi
fi

echo "chromium.sh: installing chromium with apt-get (for ${root##*/}'s report test)" >&2
export DEBIAN_FRONTEND=noninteractive
"${sudo[@]}" apt-get update -qq >&2 ||
    die "'apt-get update' failed (is the Debian mirror reachable?)"
"${sudo[@]}" apt-get install -y -qq --no-install-recommends chromium fonts-liberation >&2 ||
    die "'apt-get install chromium fonts-liberation' failed"

path="$(find_chromium)" || die "chromium was installed but is not on PATH"
"$path" --version >&2 || die "$path does not run"
echo "$path"
