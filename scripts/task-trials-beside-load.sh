#!/bin/bash
# The lab's task trials, run again and again beside two busy loops, at the test lanes' priority.
#
#     bash scripts/task-trials-beside-load.sh [ROUNDS]     # default 14 rounds of 3: 42 trials
#
# Each round runs tests/lab/test_task.py (three trials from fresh processes: the palm turning an
# off-centre grasp, the same grasp without feedback, the assist) three at a time, as the suite's
# lanes do (scripts/at-test-priority.py -5 --group -20), while two `yes` loops, each in a session
# of its own, keep both cores busy. A trip of the UR controller's RTDE watchdog fails a trial
# (the arm's keep-alive is real-time in the arm process: a busy machine must not stop the arm).
# Prints one line per round and the total; exits 1 if any trial failed. Logs: $LOGS (a temporary
# directory unless set).
set -u
ROUNDS=${1:-14}
cd "$(dirname "$0")/.."
LOGS=${LOGS:-$(mktemp -d)}
setsid yes >/dev/null &
Y1=$!
setsid yes >/dev/null &
Y2=$!
trap 'kill $Y1 $Y2 2>/dev/null' EXIT
passed=0
failed=0
for i in $(seq 1 "$ROUNDS"); do
  log="$LOGS/round-$i.log"
  .venv/bin/python scripts/at-test-priority.py -5 --group -20 -- \
    .venv/bin/python -m pytest -q -p no:cacheprovider tests/lab/test_task.py -n 3 >"$log" 2>&1
  p=$(grep -oE '[0-9]+ passed' "$log" | grep -oE '[0-9]+' || echo 0)
  f=$(grep -oE '[0-9]+ failed' "$log" | grep -oE '[0-9]+' || echo 0)
  trips=$(grep -c "the controller's watchdog stopped the robot" "$log")
  passed=$((passed + p))
  failed=$((failed + f))
  echo "round $i: $p passed, $f failed, $trips with a watchdog trip ($log)"
done
echo "$passed of $((passed + failed)) trials passed on their first run"
[ "$failed" -eq 0 ]
