#!/usr/bin/env bash
# Set up (idempotent; with the tests' tools and every optional extra) and run the test suite.
# pytest exits non-zero when no test ran.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh --test
.venv/bin/python -m pytest tests -q "$@"
