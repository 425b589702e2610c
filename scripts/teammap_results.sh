#!/usr/bin/env bash
# Evaluate a team-map run (or reference) on every standard test setting of README's team-map table,
# after choosing its test temperature on validation episodes:
#
#   scripts/teammap_results.sh runs/reference/teammap_2agents
#
# 1. harness tune --write: the Boltzmann temperature, on validation episodes of the run's own
#    training maps (eval.validation_seed; never the test episodes);
# 2. harness eval on the test episodes (eval.seed): 50x50 random maps (1000 steps), the shipped
#    cave_100x50 and maze_100x50 (1000 steps, test maps never drawn in training), 15x15 random
#    maps (150 steps), each with the tuned temperature and greedy (T = 0).
# The eval files land in the run folder (for a reference: runs/evals/<name>/, see harness eval).
# N_AGENTS=1 evaluates the same network with another team size (parameter sharing).
set -euo pipefail
run=${1:?usage: scripts/teammap_results.sh RUN_DIR}
temps=${TEMPERATURES:-0.1 0.2 0.3 0.5}
team=()
if [[ -n ${N_AGENTS:-} ]]; then team=(--set "env.n_agents=$N_AGENTS"); fi

# shellcheck disable=SC2086
harness tune "$run" --temperatures $temps --episodes "${TUNE_EPISODES:-20}" --write "${team[@]}"
settings=(
    "env.map=random"
    "env.map=cave_100x50"
    "env.map=maze_100x50"
    "env.map=random env.height=15 env.width=15 env.max_steps=150"
)
for setting in "${settings[@]}"; do
    args=()
    for kv in $setting; do args+=(--set "$kv"); done
    harness eval "$run" "${args[@]}" "${team[@]}"
    harness eval "$run" "${args[@]}" "${team[@]}" --set eval.temperature=0
done
