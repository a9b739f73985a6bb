#!/usr/bin/env bash
# Does the test suite pass every time? Runs the README's test command N times on a fresh clone.
#
#   bash scripts/flake_check.sh N [--load] [--venv PATH] [-- PYTEST_ARGS...]
#
# Clones the committed HEAD of this checkout (not its uncommitted changes) into a new temporary directory,
# sets the clone up once (scripts/setup.sh: its own .venv) and runs `bash scripts/test.sh` there N times
# (with `-- ARGS` or `--venv`: the command test.sh runs after its set-up, the same environment).
# Prints each run's result with the names of the tests that failed, then `flake: passed=K/N`; exit status
# 0 when all N passed. Each run's output is kept (the directory is printed); the clone is removed when all
# runs passed.
#
#   --load         a CPU hog beside the tests: one busy-loop process per core (nproc), started before
#                  the first run and killed at the end (also on Ctrl-C). The nodes then start, discover
#                  each other and render on a saturated machine, where timing-dependent tests fail.
#   --venv PATH    use an existing virtualenv with uw_sil's dependencies (e.g. a checkout's .venv)
#                  instead of setting one up in the clone (a few minutes). The venv is not modified:
#                  scripts/setup.sh is skipped and the tests run as scripts/test.sh runs them, with the
#                  clone first on PYTHONPATH (an editable install of another checkout is shadowed).
#   -- ARGS        pytest's arguments instead of the whole test/ directory, e.g. `-- test/test_node_faults.py
#                  -k sigkill` to repeat a subset, `-- -m "not slow"` for the quick tests.
#
# The real-ros2-tools tests (test/test_ros2_tools.py) find ../shared/ros2-cli beside the repository; the
# clone has none beside it, so $UW_SIL_ROS2_CLI is set to this checkout's when it has one.
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"

usage() { awk 'NR > 1 && !/^#/ {exit} NR > 1 {sub(/^# ?/, ""); print}' "$0" >&2; exit 2; }
[ $# -ge 1 ] || usage
n="$1"; shift
[[ "$n" =~ ^[1-9][0-9]*$ ]] || usage
load=0; venv=""; pytest_args=()
while [ $# -gt 0 ]; do
  case "$1" in
    --load) load=1; shift ;;
    --venv) [ $# -ge 2 ] || usage; venv="$(cd "$2" && pwd)"; shift 2 ;;
    --) shift; pytest_args=("$@"); break ;;
    *) usage ;;
  esac
done
if [ -n "$venv" ] && [ ! -x "$venv/bin/python" ]; then
  echo "flake_check: $venv/bin/python not found" >&2; exit 2
fi

commit="$(git -C "$here" rev-parse HEAD)"
work="$(mktemp -d "${TMPDIR:-/tmp}/uw_sil_flake.XXXXXX")"
clone="$work/repo"
hogs=()
cleanup() {
  for pid in "${hogs[@]}"; do kill "$pid" 2>/dev/null || true; done
  for pid in "${hogs[@]}"; do wait "$pid" 2>/dev/null || true; done
}
trap cleanup EXIT
trap 'exit 130' INT TERM

echo "[flake] cloning $here at $(git -C "$here" log -1 --format='%h %s' | cut -c1-80) into $clone"
git clone -q --no-hardlinks "$here" "$clone"
git -C "$clone" checkout -q --detach "$commit"
if [ -z "${UW_SIL_ROS2_CLI:-}" ] && [ -f "$here/../shared/ros2-cli/install.sh" ]; then
  export UW_SIL_ROS2_CLI="$(cd "$here/../shared/ros2-cli" && pwd)"
fi

if [ -z "$venv" ]; then
  echo "[flake] setting up the clone's .venv once (scripts/setup.sh)"
  (cd "$clone" && bash scripts/setup.sh) > "$work/setup.log" 2>&1 || {
    echo "[flake] set-up failed; see $work/setup.log" >&2; tail -20 "$work/setup.log" >&2; exit 1; }
fi

if [ "$load" = 1 ]; then
  cores="$(nproc)"
  for _ in $(seq "$cores"); do
    ( trap - INT TERM; while :; do :; done ) &
    hogs+=("$!")
  done
  echo "[flake] CPU hog: $cores busy-loop processes (pids ${hogs[*]})"
fi

# pytest lists failed and erroring tests at the end (-rfE), one line each: "FAILED test/x.py::name - ..."
export PYTEST_ADDOPTS="${PYTEST_ADDOPTS:-} -rfE -p no:cacheprovider"
passed=0
for i in $(seq "$n"); do
  log="$work/run$i.log"
  t0=$(date +%s)
  set +e
  if [ -z "$venv" ] && [ ${#pytest_args[@]} = 0 ]; then
    (cd "$clone" && bash scripts/test.sh) > "$log" 2>&1
  else
    # what scripts/test.sh runs after its set-up step, with the selection given (test.sh itself always
    # passes `test`, so a file given after it would not narrow the run); without paths pytest takes test/
    (cd "$clone" && export PYTHONPATH="$clone${PYTHONPATH:+:$PYTHONPATH}" && source scripts/pytest_args.sh \
       && exec "${venv:-$clone/.venv}/bin/python" -m pytest "${UW_SIL_PYTEST_ARGS[@]}" "${pytest_args[@]}") > "$log" 2>&1
  fi
  rc=$?
  set -e
  secs=$(( $(date +%s) - t0 ))
  summary="$( (grep -E '(passed|failed|error|skipped|deselected).* in [0-9.]+s' "$log" || true) | tail -1 \
             | sed -E 's/^=+ //; s/ =+$//')"
  if [ "$rc" = 0 ]; then
    passed=$((passed + 1))
    echo "[flake] run $i/$n: PASS in ${secs} s (${summary:-no summary})"
  else
    echo "[flake] run $i/$n: FAIL (exit $rc) in ${secs} s (${summary:-no summary}); log $log"
    failed="$(grep -E '^(FAILED|ERROR) ' "$log" | sed -E 's/ - .*//' || true)"
    if [ -n "$failed" ]; then
      sed 's/^/[flake]     /' <<< "$failed"
    else
      tail -5 "$log" | sed 's/^/[flake]     | /'
    fi
  fi
done
echo "[flake] logs in $work"
if [ "$passed" = "$n" ]; then
  rm -rf "$clone"
fi
echo "flake: passed=$passed/$n"
[ "$passed" = "$n" ]
