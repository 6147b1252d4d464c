#!/usr/bin/env bash
# Train every shipped policy: each line of sweep_jobs.txt is "scenario algo reward seed episodes",
# run two at a time (one per core) through benchmarks/train_policies.py; then select and ship
# the best seed of every method. Re-running resumes unfinished runs and skips finished ones.
#   nohup bash benchmarks/sweep.sh > runs/sweep.log 2>&1 &
set -u
cd "$(dirname "$0")/.."
jobs=${1:-benchmarks/sweep_jobs.txt}
run_one() {
  read -r scenario algo reward seed episodes <<< "$1"
  done_file="runs/$scenario/$algo-$reward-s$seed.done"
  [ -e "$done_file" ] && { echo "skip $1"; return 0; }
  echo "$(date +%T) start $1"
  if python benchmarks/train_policies.py --scenario "$scenario" --algo "$algo" \
      --reward "$reward" --seeds "$seed" --episodes "$episodes" > /dev/null; then
    touch "$done_file"; echo "$(date +%T) done $1"
  else
    echo "$(date +%T) FAILED $1 (see runs/$scenario/$algo-$reward-s$seed.log)"
  fi
}
export -f run_one
grep -v '^\s*$' "$jobs" | xargs -P 2 -I{} bash -c 'run_one "{}"'
# Ship the best validation seed of every method among the seeds that finished.
for method in $(awk '{print $1":"$2":"$3}' "$jobs" | sort -u); do
  IFS=: read -r scenario algo reward <<< "$method"
  seeds=$(ls runs/"$scenario"/"$algo-$reward"-s*.done 2>/dev/null | sed 's/.*-s\([0-9]*\)\.done/\1/' | tr '\n' ' ')
  [ -n "$seeds" ] && python benchmarks/train_policies.py --scenario "$scenario" --algo "$algo" \
    --reward "$reward" --seeds $seeds --episodes 0 --ship-only > /dev/null && echo "shipped $method from seeds $seeds"
done
echo "$(date +%T) SWEEP DONE"
