# Does issue 16's time reward (ipf-time) shorten the entity policy's time on 20v20?
# Both arms start from the parked arm's 20v20 policy (../bicnet-e-parked/parked.safetensors,
# a policy file, so the critic starts fresh: --critic-warmup 400 updates), shield in the loop,
# parked bit, 3000 episodes of 20v20; "time" uses ipf-time, "control" the plain ipf reward.
# Usage: bash command.sh time|control   (code at the commit that added this file)
set -e
arm=$1
reward=ipf
if [ "$arm" = time ]; then reward=ipf-time; fi
agv train --algo bicnet-e --reward $reward --preset fast --seed 0 --eval-every 500 \
  --eval-episodes 100 --checkpoint-every 500 --set noise_start=0.1 --set noise_end=0.05 \
  --set noise_decay_episodes=1000 --set shield=true --set margin_moving=true \
  --set parked_token=true --threads 1 --no-progress --scenario 20v20 --episodes 3000 \
  --critic-warmup 400 --run-dir runs/entity/bicnet-e-time/$arm \
  --init-from benchmarks/results/scale/entity/bicnet-e-parked/parked.safetensors
