# 2000 more episodes of 20v20 with the shield in the loop and the parked bit, from the end of
# the parked arm's 20v20 stage (command.sh), with shield_penalty=1 and without it (control).
# Code at commit f2184ae. Usage: bash penalty.sh penalty|penalty5|continued (penalty5: C = 5, added at commit 979ab18)
set -e
arm=$1
extra=""
if [ "$arm" = penalty ]; then extra="--set shield_penalty=1.0"; fi
if [ "$arm" = penalty5 ]; then extra="--set shield_penalty=5.0"; fi
agv train --algo bicnet-e --reward ipf --preset fast --seed 0 --eval-every 500 --eval-episodes 100 --checkpoint-every 500 --set noise_start=0.1 --set noise_decay_episodes=1000 --set shield=true --set margin_moving=true --set parked_token=true --threads 1 --no-progress $extra --scenario 20v20 --episodes 2000 --run-dir runs/entity/bicnet-e-parked/$arm-20v20 --init-from runs/entity/bicnet-e-parked/parked/stage-2-20v20
