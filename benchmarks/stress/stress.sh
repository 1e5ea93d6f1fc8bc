#!/usr/bin/env bash
# Run tests repeatedly under CPU load: two busy loops beside pytest, killed on exit.
#   bash benchmarks/stress/stress.sh LOG --rep 50 tests/test_acquire_faults.py -k sigint
set -u
log=$1; shift
here="$(cd "$(dirname "$0")" && pwd)"
cd "$here/../.."
python3 -c 'while True: pass' & b1=$!
python3 -c 'while True: pass' & b2=$!
trap 'kill $b1 $b2 2>/dev/null' EXIT
PYTHONPATH="$here" timeout 5400 .venv/bin/python -m pytest -p repplug -q -n 0 -p no:cacheprovider "$@" > "$log" 2>&1
echo "rc=$?" >> "$log"
