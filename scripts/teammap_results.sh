#!/usr/bin/env bash
# Evaluate a team-map run (or reference) on the standard test settings of README's team-map
# table, after choosing its test temperature on validation episodes:
#
#   scripts/teammap_results.sh runs/teammap_2agents-<time>             # all settings
#   SETTINGS=random scripts/teammap_results.sh runs/teammap_2agents-<time>   # 50x50 only
#
# 1. harness tune --write: the Boltzmann temperature, on validation episodes of the run's own
#    training maps (eval.validation_seed; never the test episodes), with the run's eval.shield;
# 2. harness eval on the test episodes (eval.seed): 50x50 random maps (1000 steps; also greedy
#    and without the wall shield), the shipped cave_100x50 and maze_100x50 (1000 steps; test
#    maps, never drawn in training) and 15x15 random maps (150 steps).
# The eval files land in the run folder (for a reference: runs/evals/<name>/, see harness eval).
# N_AGENTS=1 plays the same network with another team size (parameter sharing).
# A run trained with algo.action_mask is tested behind the mask only (no unshielded row).
set -euo pipefail
run=${1:?usage: scripts/teammap_results.sh RUN_DIR}
temps=${TEMPERATURES:-0.1 0.2 0.3 0.5}
team=()
if [[ -n ${N_AGENTS:-} ]]; then team=(--set "env.n_agents=$N_AGENTS"); fi

if [[ -z ${NO_TUNE:-} ]]; then
    # shellcheck disable=SC2086
    harness tune "$run" --temperatures $temps --episodes "${TUNE_EPISODES:-20}" --write "${team[@]}"
fi
declare -A setting=(
    [random]="env.map=random"
    [cave]="env.map=cave_100x50"
    [maze]="env.map=maze_100x50"
    [15x15]="env.map=random env.height=15 env.width=15 env.max_steps=150"
)
for name in ${SETTINGS:-random cave maze 15x15}; do
    args=()
    for kv in ${setting[$name]}; do args+=(--set "$kv"); done
    harness eval "$run" "${args[@]}" "${team[@]}"
    if [[ $name == random ]]; then
        harness eval "$run" "${args[@]}" "${team[@]}" --set eval.temperature=0
        if ! grep -Eq '^\s*action_mask:\s*true' "$run/config.yaml"; then
            harness eval "$run" "${args[@]}" "${team[@]}" --set eval.shield=false
        fi
    fi
done
