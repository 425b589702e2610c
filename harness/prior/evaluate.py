"""``harness eval PRIOR_RUN``: a map prior scored on the test episodes' partial maps.

The partial maps are those of ``--episodes`` test episodes (``eval.seed``, or ``--seed``) played
by the run's ``prior.planner``, ``prior.snapshots`` an episode, on the run's env (``--set
env.map=...`` scores it on other maps: a prior of another family, or random maps). The result
(:func:`harness.prior.score.score`'s keys, with the episodes' seed, count and env) is saved
where the run's results go (``eval.json``, or a file named by the settings), as a policy's is.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from harness.config.loading import load_config, parse_yaml
from harness.results.rundir import RunDir, result_filename, results_folder, write_json


def is_prior_run(path: Path | str) -> bool:
    """Whether ``path`` is the folder of a prior run (its ``config.yaml`` has a ``prior:``
    section); read as YAML only, nothing of it built."""
    run = RunDir(path)
    if not Path(path).is_dir() or not run.is_run:
        return False
    try:
        raw = parse_yaml(run.config.read_text(encoding="utf-8"), str(run.config))
    except (OSError, ValueError):
        return False
    return isinstance(raw, dict) and raw.get("prior") is not None


def evaluate_prior(
    path: Path, overrides: Sequence[str], episodes: int, seed: int | None = None
) -> dict[str, Any]:
    """Score the prior run at ``path`` (its ``model.zip``) and save the result.

    Returns:
        The summary, with the saved file as ``"saved"``.

    Raises:
        ValueError: one line (a config error, a missing or damaged ``model.zip``).
    """
    from harness.prior.data import record  # torch only here
    from harness.prior.model import load_prior
    from harness.prior.score import score

    run = RunDir(path)
    config = load_config(run.config, overrides)
    assert config.prior is not None
    seed = config.eval.seed if seed is None else seed
    seed_changed = None if seed == config.eval.seed else str(seed)
    out = RunDir(results_folder(run.path)).result(
        result_filename("eval", overrides, "model", episodes, seed_changed)
    )
    prior = load_prior(run.path)
    sets = record(config.env, config.prior.planner, episodes, seed, config.prior.snapshots)
    summary: dict[str, Any] = {
        "prior": str(run.model),
        "seed": seed,
        "episodes": episodes,
        "planner": config.prior.planner,
        "overrides": list(overrides),
        "env": config.env.model_dump(mode="json"),
        **score(prior.wall_probability, sets),
    }
    summary["saved"] = str(write_json(out, summary))
    return summary


def format_prior(summary: dict[str, Any]) -> str:
    """The summary in words (``harness eval PRIOR_RUN`` without ``--json``)."""
    return (
        f"{summary['prior']}: {summary['maps']:,} partial maps of {summary['episodes']} episodes "
        f"(seed {summary['seed']}, {summary['planner']}), {summary['cells']:,} unseen cells\n"
        f"  unseen_logloss  {summary['unseen_logloss']:.4f}\n"
        f"  density_logloss {summary['density_logloss']:.4f}  (the seen cells' wall share)\n"
        f"  ratio           {summary['ratio']:.3f}"
    )
