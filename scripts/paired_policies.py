"""Two variants of a baseline (``--policy``) on the same episodes, compared episode by episode:
``harness eval --against`` compares with a baseline under the *same* config, so it cannot set
the two apart where they differ only in a key (the rollout chooser with and without
``eval.rollout.prior``). Each variant is the config with its own ``--set`` overrides (``--a``,
``--b``, repeatable), played with ``harness eval``'s own code; printed: each mean coverage and
the mean paired difference (a minus b, points) with its 95 % bootstrap interval
(``harness.results.stats.paired_difference``, the one ``--against`` uses).

    python scripts/paired_policies.py rollout configs/goals_2agents.yaml \
        --set env.map=random --episodes 30 \
        --a eval.rollout.prior=runs/reference/prior_random \
        --out docs/baselines/rollout_prior/random_2agents_prior_vs_uniform.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from harness.commands import evaluate, resolve_target
from harness.results.stats import paired_difference


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("policy")
    parser.add_argument("config")
    parser.add_argument("--set", dest="common", action="append", default=[])
    parser.add_argument("--a", action="append", default=[])
    parser.add_argument("--b", action="append", default=[])
    parser.add_argument("--episodes", type=int, default=30)
    parser.add_argument("--seed", type=int)
    parser.add_argument("--out", type=Path, help="also write the comparison as JSON")
    args = parser.parse_args()
    coverage, summaries = {}, {}
    for name, own in (("a", args.a), ("b", args.b)):
        overrides = [*args.common, *own]
        target = resolve_target(None, args.policy, args.config, overrides, args.seed)
        summary, _ = evaluate(target, args.episodes, overrides)
        coverage[name] = np.asarray(summary["coverage"], dtype=np.float64)
        summaries[name] = {"overrides": overrides, "seed": summary["seed"]}
        print(f"{name} {own}: mean coverage {100 * coverage[name].mean():.2f} %", flush=True)
    a, b = coverage["a"], coverage["b"]
    difference, low, high = paired_difference(a, b)
    print(
        f"a - b: {100 * difference:+.2f} [{100 * low:+.2f}, {100 * high:+.2f}] points "
        f"(ahead {(a > b).sum()}, behind {(a < b).sum()}, equal {(a == b).sum()})"
    )
    if args.out is not None:
        result = {
            "policy": args.policy,
            "config": args.config,
            "episodes": args.episodes,
            **{f"{k}_{key}": v for k, s in summaries.items() for key, v in s.items()},
            "a_mean": float(a.mean()),
            "b_mean": float(b.mean()),
            "difference": difference,
            "difference_ci95": [low, high],
            "ahead": int((a > b).sum()),
            "behind": int((a < b).sum()),
            "equal": int((a == b).sum()),
            "a_coverage": a.tolist(),
            "b_coverage": b.tolist(),
        }
        args.out.write_text(json.dumps(result, indent=2) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()
