#!/usr/bin/env bash
# Runs every test of the project on a fresh machine: installs what the tests need, builds once
# (release profile, one shared target directory) and runs the whole workspace's tests.
set -euo pipefail
cd "$(dirname "$0")/.."
export CARGO_TERM_COLOR=${CARGO_TERM_COLOR:-never}
cargo build --workspace --release --all-targets
cargo test --workspace --release
