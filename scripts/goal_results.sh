#!/usr/bin/env bash
# Evaluate a goal-selection run (or reference, or each run of a seed group) on the test settings
# of docs/results.md "Learned goal selection": 100 test episodes each (the config's eval.seed,
# the episodes of docs/baselines/), greedy (the config's eval.temperature: 0):
#
#   scripts/goal_results.sh runs/goals_2agents-<time>                 # every setting
#   SETTINGS="random random1 random4" scripts/goal_results.sh RUN     # some of them
#
# Settings: random (50x50, the run's 2 agents), random1 / random4 (1 and 4 agents: the same
# network, parameter sharing), cave / cave4 and maze / maze4 (the shipped test maps, never drawn
# in training, 2 and 4 agents). The eval files land in the run folder (for a reference:
# runs/evals/<name>/, see harness eval).
set -euo pipefail
run=${1:?usage: scripts/goal_results.sh RUN_DIR}
declare -A setting=(
    [random]="env.map=random"
    [random1]="env.map=random env.n_agents=1"
    [random4]="env.map=random env.n_agents=4"
    [cave]="env.map=cave_100x50"
    [cave4]="env.map=cave_100x50 env.n_agents=4"
    [maze]="env.map=maze_100x50"
    [maze4]="env.map=maze_100x50 env.n_agents=4"
)
for name in ${SETTINGS:-random random1 random4 cave cave4 maze maze4}; do
    args=()
    for kv in ${setting[$name]}; do args+=(--set "$kv"); done
    harness eval "$run" "${args[@]}" --episodes "${EPISODES:-100}"
done
