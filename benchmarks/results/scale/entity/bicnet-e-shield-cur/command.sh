# The shield in the loop for the 10v10 and 20v20 stages, from the shipped run's 6v6 stage
# (runs/entity/bicnet-e-ipf-s0: allocator/weights/any/README.md); code at commit a204543.
set -e
common="--algo bicnet-e --reward ipf --preset fast --seed 0 --eval-every 500 --eval-episodes 100 --checkpoint-every 500 --set noise_start=0.3 --set noise_decay_episodes=3000 --set shield=true --no-progress"
agv train $common --scenario 10v10 --episodes 3000 --run-dir runs/entity/bicnet-e-shield-cur/stage-1-10v10 --init-from runs/entity/bicnet-e-ipf-s0/stage-0-6v6
agv train $common --scenario 20v20 --episodes 2000 --run-dir runs/entity/bicnet-e-shield-cur/stage-2-20v20 --init-from runs/entity/bicnet-e-shield-cur/stage-1-10v10
