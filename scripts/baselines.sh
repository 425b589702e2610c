#!/usr/bin/env bash
# Regenerate the stored baseline evaluations, docs/baselines/<config>[-env.max_steps-N]-<policy>.json,
# that README's tables quote (tests/test_readme_results.py checks the tables against them).
#
#   scripts/baselines.sh                            # all of them (~10 min on 2 cores)
#   scripts/baselines.sh cave_2agents cave_4agents  # only these configs (their own max_steps)
#
# EPISODES (default 100) and OUT (default docs/baselines) override the episode count and folder;
# POLICIES (default "random local frontier") the baselines, e.g. POLICIES=frontier. The written
# planners' table (docs/results.md, scripts/planner_table.py) was made with
#   POLICIES="frontier frontier_pocket frontier_utility frontier_minpos frontier_hungarian" \
#   scripts/baselines.sh ddqn_1agent ddqn_2agents ddqn_3agents ddqn_4agents ddqn_15x15 \
#   cave_2agents cave_4agents maze_2agents maze_4agents
set -euo pipefail
cd "$(dirname "$0")/.."
episodes=${EPISODES:-100}
out=${OUT:-docs/baselines}
mkdir -p "$out"

# config[:max_steps]; a max_steps suffix evaluates the config with --set env.max_steps=N.
all=(ddqn_15x15 dueling_15x15 ddqn_1agent ddqn_1agent:500 ddqn_1agent:2000 ddqn_2agents
     ddqn_3agents ddqn_4agents cave_2agents cave_4agents maze_2agents maze_4agents)
if (( $# )); then targets=("$@"); else targets=("${all[@]}"); fi

for target in "${targets[@]}"; do
    config=${target%%:*}
    args=(--config "configs/$config.yaml" --episodes "$episodes" --json)
    name=$config
    if [[ $target == *:* ]]; then
        args+=(--set "env.max_steps=${target#*:}")
        name+="-env.max_steps-${target#*:}"
    fi
    for policy in ${POLICIES:-random local frontier}; do
        # write to a temporary file first, so a failed evaluation never leaves half a file
        tmp="$out/$name-$policy.json.tmp"
        if ! harness eval --policy "$policy" "${args[@]}" > "$tmp"; then
            rm -f "$tmp"
            exit 2
        fi
        mv "$tmp" "$out/$name-$policy.json"
        echo "wrote $out/$name-$policy.json"
    done
done
