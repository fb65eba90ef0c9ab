#!/usr/bin/env bash
# Creates (once) the Python environment the tests use and prints its interpreter's path.
#
#   scripts/python-env.sh            -> last line of stdout: /abs/path/to/target/pyenv/bin/python
#
# The venv lives at <workspace>/target/pyenv (override with SCANCORR_PYENV) and holds exactly
# the pinned packages of tests/python/requirements.txt, then the project's Python package
# (`pip install ./clients/python`, as a user installs it). pip runs only when the venv is new
# or the requirements, the package's sources (or the base interpreter) changed since the last
# successful install, so after the first run this works offline. Everything but the final
# path goes to stderr.
# The base interpreter is $PYTHON if set, else python3 (Python >= 3.9 with the venv module).
set -euo pipefail

root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
req="$root/tests/python/requirements.txt"
venv="${SCANCORR_PYENV:-$root/target/pyenv}"
base="${PYTHON:-python3}"

die() {
    echo "python-env.sh: error: $*" >&2
    exit 1
}

[ -f "$req" ] || die "missing $req"
command -v "$base" >/dev/null 2>&1 ||
    die "no Python interpreter '$base' on PATH: install Python 3 (>= 3.9) with pip and venv, or set PYTHON"

mkdir -p "$(dirname "$venv")"

# Serialize concurrent callers (several test binaries may ask at once).
lock="$venv.lock"
if command -v flock >/dev/null 2>&1; then
    exec 9>"$lock"
    flock 9
fi

py="$venv/bin/python"
stamp="$venv/.requirements.stamp"

base_id="$("$base" -c 'import sys; print(sys.implementation.name, *sys.version_info[:3])')" ||
    die "'$base' does not run"
want="$( { echo "$base_id"; cat "$req"; } | (sha256sum 2>/dev/null || shasum -a 256) | cut -d' ' -f1)"

# A venv whose interpreter no longer runs (base Python upgraded or moved) is rebuilt.
if [ -d "$venv" ] && ! "$py" -c 'import sys' >/dev/null 2>&1; then
    echo "python-env.sh: $venv is broken, recreating it" >&2
    rm -rf "$venv"
fi

if [ ! -x "$py" ]; then
    echo "python-env.sh: creating $venv with $base ($base_id)" >&2
    if ! "$base" -m venv "$venv" >&2; then
        rm -rf "$venv"
        die "'$base -m venv' failed: install the venv module (e.g. apt-get install python3-venv)"
    fi
fi

if [ "$(cat "$stamp" 2>/dev/null || true)" != "$want" ]; then
    echo "python-env.sh: installing $(grep -cEv '^\s*(#|$)' "$req") pinned packages from ${req#"$root"/}" >&2
    rm -f "$stamp"
    PIP_DISABLE_PIP_VERSION_CHECK=1 PIP_NO_INPUT=1 \
        "$py" -m pip install --quiet -r "$req" >&2 ||
        die "pip install -r $req failed (is PyPI reachable?)"
    echo "$want" >"$stamp"
fi

# The project's package: reinstalled when its sources change (not editable: the tests use it
# as installed).
pkg="$root/clients/python"
pkg_stamp="$venv/.scancorr-package.stamp"
pkg_want="$( (cd "$pkg" && find pyproject.toml README.md scancorr -type f ! -name '*.pyc' | LC_ALL=C sort | xargs cat) |
    (sha256sum 2>/dev/null || shasum -a 256) | cut -d' ' -f1)"
if [ "$(cat "$pkg_stamp" 2>/dev/null || true)" != "$pkg_want" ]; then
    echo "python-env.sh: installing the scancorr package from clients/python" >&2
    rm -f "$pkg_stamp"
    PIP_DISABLE_PIP_VERSION_CHECK=1 PIP_NO_INPUT=1 \
        "$py" -m pip install --quiet --no-deps --no-build-isolation --force-reinstall "$pkg" >&2 ||
        die "pip install clients/python failed"
    rm -rf "$pkg/build" "$pkg"/*.egg-info
    echo "$pkg_want" >"$pkg_stamp"
fi

echo "$py"
