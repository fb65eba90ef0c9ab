#!/usr/bin/env bash
# Runs every test of the project on a fresh machine: installs what the tests need (a Python
# venv with the MCAP and protobuf readers, headless Chromium for the report test), builds once
# (release profile, one shared target directory) and runs the whole workspace's tests.
set -euo pipefail
cd "$(dirname "$0")/.."
export CARGO_TERM_COLOR=${CARGO_TERM_COLOR:-never}
./scripts/python-env.sh >/dev/null
if [ -x scripts/chromium.sh ]; then ./scripts/chromium.sh >/dev/null; fi
cargo build --workspace --release --all-targets
cargo test --workspace --release
