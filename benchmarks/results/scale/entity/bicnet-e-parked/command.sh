# The parked bit (parked_token) with the shield in the loop, 10v10 and 20v20 stages, from the
# default-preset 6v6 run's portable copy (20,973 episodes; bicnet-e-default-s0/), beside a
# control without the bit (same settings otherwise). Code at commit 3edba78.
# Usage: bash command.sh parked|control
set -e
arm=$1
extra=""
if [ "$arm" = parked ]; then extra="--set parked_token=true"; fi
common="--algo bicnet-e --reward ipf --preset fast --seed 0 --eval-every 500 --eval-episodes 100 --checkpoint-every 500 --set noise_start=0.3 --set noise_decay_episodes=3000 --set shield=true --set margin_moving=true --threads 1 --no-progress $extra"
out=runs/entity/bicnet-e-parked/$arm
agv train $common --scenario 10v10 --episodes 3000 --run-dir $out/stage-1-10v10 --init-from benchmarks/results/scale/entity/bicnet-e-default-s0
agv train $common --scenario 20v20 --episodes 2000 --run-dir $out/stage-2-20v20 --init-from $out/stage-1-10v10
