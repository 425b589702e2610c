"""What ``harness eval``, ``tune``, ``compare``, ``render`` and ``export`` do, apart from parsing
arguments and printing.

A *target* is what gets evaluated: a trained model (a run folder or a model zip, with the run's
``config.yaml``) or a baseline (``--policy random|local|frontier`` with ``--config``). ``eval``,
``tune`` and ``render`` resolve it the same way, so a baseline and a model are measured on the same
episodes.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import itertools
import json
import math
import os
import shutil
import sys
import tempfile
import zipfile
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from harness.config.loading import config_from_dict, load_config, parse_override
from harness.config.schema import ConfigError, ExperimentConfig
from harness.evaluation.baselines import BASELINES, make_baseline
from harness.evaluation.episodes import (
    BatchPolicy,
    headline,
    model_policy,
    run_episodes,
    selection_score,
    summarize,
)
from harness.factory import make_env
from harness.results.rundir import (
    REFERENCE_FILES,
    STANDARD_EPISODES,
    CheckpointDir,
    RunDir,
    RunDirError,
    against_filename,
    atomic_write,
    atomic_write_text,
    check_output_file,
    inside,
    is_reference,
    log_header,
    result_filename,
    results_folder,
    write_json,
)
from harness.tasks import TASKS, Task, task_of, task_of_columns, task_of_summary
from harness.tasks.base import TooManyFrames, sampling_note

#: Episodes of a standard evaluation (the thesis tested on 100).
DEFAULT_EPISODES = STANDARD_EPISODES


class TargetError(ValueError):
    """A model, run folder or baseline that cannot be used, with a one-line message."""


#: Most bytes the files of a model zip may unpack to, together. SB3 reads each file of the zip
#: into memory (and torch then builds the tensors from it), so a small zip that declares huge
#: files, such as a few MB of deflated zeros, would take gigabytes of memory before any error.
#: The largest model of this project unpacks to under 5 MB: 1 GiB leaves two hundred times that.
MAX_MODEL_UNPACKED = 1 << 30


def check_model_zip(model: Path | bytes, name: Path | str) -> None:
    """Refuse a model zip (a file, or its bytes) whose files unpack to more than
    :data:`MAX_MODEL_UNPACKED` bytes, from the sizes its directory declares, before anything is
    unpacked (Python's ``zipfile``, which SB3 uses, never unpacks past a declared size).

    Raises:
        TargetError: naming ``name`` and the sizes, or the zip's damage when it cannot be read.
    """
    try:
        with zipfile.ZipFile(io.BytesIO(model) if isinstance(model, bytes) else model) as archive:
            items = archive.infolist()
    except Exception as exc:  # a damaged zip raises zipfile, OSError, EOFError or struct errors
        raise TargetError(f"{name}: cannot load model ({type(exc).__name__}: {exc})") from None
    total = sum(item.file_size for item in items)
    if total > MAX_MODEL_UNPACKED:
        largest = max(items, key=lambda item: item.file_size)
        raise TargetError(
            f"{name}: its files unpack to {total:,} bytes (largest {largest.filename!r}: "
            f"{largest.file_size:,}), over the {MAX_MODEL_UNPACKED:,} a model may take; not loaded"
        )


@dataclass
class Target:
    """A policy with the config it is evaluated under."""

    policy: BatchPolicy
    config: ExperimentConfig
    label: str
    run_dir: Path | None
    """The run folder of a trained model (where ``eval.json`` goes), else ``None``."""
    seed: int
    """Seed of the episodes: the one asked for, else the config's ``eval.seed``."""
    model_name: str = "model"
    """The model's path in its run folder without ``.zip`` (for the eval file's name)."""
    model: Any = None
    """The loaded SB3 model of a trained target (``None`` for a baseline)."""

    @property
    def seed_changed(self) -> str | None:
        """The episodes' seed where it is not the config's ``eval.seed`` (it then names the
        result files: :func:`~harness.results.rundir.result_filename`), else ``None``."""
        return None if self.seed == self.config.eval.seed else str(self.seed)

    @property
    def results_dir(self) -> Path | None:
        """Where eval, tune and render results go: the run folder, or ``runs/evals/<name>/``
        for an exported reference (never changed by evaluating it); ``None`` for a baseline."""
        return None if self.run_dir is None else results_folder(self.run_dir)


def find_run_config(model_path: Path) -> Path:
    """``config.yaml`` of the run a model zip belongs to: beside it, or two folders up for a
    checkpoint's ``checkpoints/step-N/model.zip``.

    A checkpoint's folder holds a ``config.yaml`` too, but that is the copy a resume compares
    the run's config with: the model's results and ``tune --write`` go to the run, never into
    a checkpoint (deleted when newer checkpoints replace it, and a changed copy would make the
    run's resume refuse a config nobody edited).
    """
    beside = RunDir(model_path.parent)
    above = beside.checkpoint_of
    for run in (above, beside) if beside.is_checkpoint else (beside, above):
        if run.is_run:
            return run.config
    raise TargetError(f"{model_path}: no config.yaml of its run beside it")


def load_model_target(path: Path, overrides: Sequence[str], seed: int | None) -> Target:
    """A trained model: ``path`` is a run folder (its ``model.zip``), a checkpoint's folder (its
    ``model.zip``, evaluated for its run) or a model zip."""
    from harness.prior.evaluate import is_prior_run

    if path.is_dir() and is_prior_run(path):
        raise TargetError(
            f"{path} is a map prior's run, not a policy: score it with harness eval {path}, "
            f"plan with it with --policy rollout --set eval.rollout.prior={path}"
        )
    if path.is_dir() and RunDir(path).is_checkpoint:
        CheckpointDir(path).check_inside()  # its model and files: inside its run, links resolved
        model_path = CheckpointDir(path).model
        if not model_path.is_file():
            raise TargetError(f"{path}: a checkpoint without its model.zip")
        config_path = find_run_config(model_path)
    elif path.is_dir():
        if not RunDir(path).is_run:
            raise TargetError(f"{path}: not a run folder (no config.yaml)")
        model_path, config_path = RunDir(path).model, RunDir(path).config
        if not model_path.is_file():
            raise TargetError(
                f"{path}: no model.zip yet (training unfinished? `harness run --resume {path}`)"
            )
    elif path.is_file() and path.suffix.lower() in (".yaml", ".yml"):
        raise TargetError(
            f"{path} is a config, not a run or a model: evaluate a baseline on it with "
            f"--policy NAME --config {path}, or train it first (harness run {path})"
        )
    elif path.is_file():
        model_path, config_path = path, find_run_config(path)
    else:
        raise TargetError(f"{path}: no such run folder or model file")
    config = load_config(config_path, overrides)
    check_model_zip(model_path, model_path)
    from harness.sb3.dqn import DoubleDQN, OldModelError  # torch and SB3 only when a model is used

    try:
        # SB3 zips hold pickled objects: load only files you trust (see README).
        model = DoubleDQN.load(model_path, device="cpu")
    except OldModelError as exc:  # its own line: it names the command that migrates the model
        raise TargetError(str(exc)) from None
    except Exception as exc:  # a damaged zip raises zipfile, pickle, torch or KeyError errors
        raise TargetError(
            f"{model_path}: cannot load model ({type(exc).__name__}: {exc})"
        ) from None
    check_model_fits(model, model_path, config, _trained_sharing(config_path, config, overrides))
    run_dir = config_path.parent
    seed = config.eval.seed if seed is None else seed
    # The model's place in its run folder names the eval file ("best_model", ...): taken from the
    # path as given, so that a symlink to a model elsewhere is named like the link.
    name = Path(os.path.relpath(model_path.absolute(), run_dir.absolute())).with_suffix("")
    ev = config.eval
    policy = model_policy(model, ev.temperature, ev.shield)
    return Target(policy, config, str(model_path), run_dir, seed, name.as_posix(), model)


def _trained_sharing(
    config_path: Path, config: ExperimentConfig, overrides: Sequence[str]
) -> str | None:
    """The ``algo.sharing`` a run's model was trained with: its own config's, read again
    without the ``--set`` overrides where there are some (``None`` where it no longer loads
    without them: the model's own record is checked then)."""
    if not overrides:
        return config.algo.sharing
    try:
        return load_config(config_path).algo.sharing
    except ConfigError:
        return None


def check_model_fits(
    model: Any, model_path: Path, config: ExperimentConfig, trained_sharing: str | None = None
) -> None:
    """Refuse a model whose observation or action space is not its config's env's (a zip of
    another experiment, or made for another observation kind or team size), or whose networks
    are not the env's agents' (:func:`check_team_size`; ``trained_sharing``: the
    ``algo.sharing`` of the run's own config, before ``--set``)."""
    env = make_env(config.env)
    agent = env.possible_agents[0]
    check_team_size(model, model_path, config, env.observation_space(agent), trained_sharing)
    for what, expected, got in (
        ("observation", env.observation_space(agent), model.observation_space),
        ("action", env.action_space(agent), model.action_space),
    ):
        if _space_layout(expected) != _space_layout(got):
            raise TargetError(
                f"{model_path}: the model's {what} space {got} is not its config's env's "
                f"{expected} (a model of another experiment?)"
            )


def trained_team_size(model: Any, env_space: Any, n_agents: int) -> int | None:
    """The team size a model with agent indication was trained with, read from the model: its
    parameter sets (per-agent policy) or the width of its agent-id input; ``None`` without one.

    Args:
        model: The loaded model.
        env_space: The observation space of the env it is to play (with its agent id).
        n_agents: That env's team size.
    """
    from envs.coverage.observations import AGENT_ID_KEY
    from harness.sb3.policies import PerAgentQNetwork

    if isinstance(model.q_net, PerAgentQNetwork):
        return model.q_net.n_agents
    space = model.observation_space
    if hasattr(space, "spaces") and isinstance(space.spaces, dict):
        return int(space.spaces[AGENT_ID_KEY].shape[0]) if AGENT_ID_KEY in space.spaces else None
    base = env_space.shape[0] - n_agents  # the observation's width without the one-hot index
    trained = int(space.shape[0]) - base
    return trained if trained >= 1 else None


def check_team_size(
    model: Any,
    model_path: Path,
    config: ExperimentConfig,
    env_space: Any,
    trained_sharing: str | None = None,
) -> None:
    """Refuse to play a model with networks for other agents than the env's: under another
    ``algo.sharing`` than it was trained with (``--set``; ``trained_sharing``: the run's own, a
    ``per_group`` model records its groups), a ``shared_id`` or ``per_agent`` model for another
    team size (one parameter set, or one agent-id input, per trained agent; a ``shared`` model
    plays any team size), a ``per_group`` model for other groups: their number, and where the
    model records them (models saved since it does), their names, order and agents."""
    sharing = config.algo.sharing
    groups = getattr(model.policy, "groups", None)  # a per_group model's, in index order
    trained_as = "per_group" if groups else (trained_sharing or sharing)
    if trained_as != sharing:
        raise TargetError(
            f"{model_path}: the model was trained with algo.sharing: {trained_as} "
            f"({_networks(trained_as, model, groups)}); --set algo.sharing={sharing} asks for "
            f"{_networks(sharing)} (a model plays with the sharing it was trained with)"
        )
    if sharing == "shared":
        return
    width = config.env.id_width  # (the team size; the groups for per_group)
    trained = trained_team_size(model, env_space, width)
    if trained is not None and trained != width:
        if sharing == "per_group":
            raise TargetError(
                f"{model_path}: this algo.sharing=per_group model has one network per group "
                f"for {trained} groups; it cannot play the env's {width} groups"
            )
        what = "one network per agent" if sharing == "per_agent" else "an agent-id input per agent"
        raise TargetError(
            f"{model_path}: this algo.sharing={sharing} model has {what} for {trained} agents; "
            f"it cannot play env.n_agents={config.env.n_agents} (only algo.sharing=shared models "
            "play any team size)"
        )
    env_groups = config.env.groups if groups else None
    if env_groups is not None and list(env_groups.items()) != list(groups.items()):
        raise TargetError(
            f"{model_path}: this algo.sharing=per_group model has one network per group for the "
            f"groups {_groups_text(groups)}; the env's groups are {_groups_text(env_groups)} "
            "(it plays the groups it was trained for only)"
        )


def _networks(sharing: str, model: Any = None, groups: dict[str, Any] | None = None) -> str:
    """What a kind of sharing gives each agent, in a few words; with ``model`` (trained so),
    for how many agents or which groups."""
    if sharing == "per_group" and groups:
        return f"{len(groups)} groups: {_groups_text(groups)}"
    n = getattr(model.q_net, "n_agents", None) if model is not None else None
    each = "per" if n is None else f"for each of {n}"
    return {
        "shared": "one network for every agent",
        "shared_id": "one network that reads each agent's id",
        "per_agent": f"one network {each} agent{'s' if n else ''}",
        "per_group": f"one network {each} group{'s' if n else ''}",
    }.get(sharing, sharing)


def _groups_text(groups: dict[str, Any]) -> str:
    """Groups as ``env.pettingzoo.groups`` is written: ``{a: [a_0, a_1], b: [b_0]}``."""
    return (
        "{" + ", ".join(f"{name}: [{', '.join(agents)}]" for name, agents in groups.items()) + "}"
    )


def _space_layout(space: Any) -> Any:
    """What a network needs to match: kind, shape and dtype (per key of a ``Dict``), or the
    number of actions. Bounds may differ (raw coordinates on a map of another size)."""
    if hasattr(space, "spaces") and isinstance(space.spaces, dict):
        return {key: _space_layout(sub) for key, sub in space.spaces.items()}
    if hasattr(space, "n"):
        return ("discrete", int(space.n))
    return (type(space).__name__, tuple(space.shape), str(space.dtype))


def resolve_target(
    target: Path | None,
    policy: str | None,
    config_path: Path | None,
    overrides: Sequence[str],
    seed: int | None,
) -> Target:
    """Resolve the command line's target (see the module docstring)."""
    if policy is not None:
        if target is not None:
            raise TargetError("give either a run/model or --policy, not both")
        if config_path is None:
            raise TargetError(f"--policy {policy} needs --config CONFIG.yaml")
        if policy not in BASELINES:
            raise TargetError(f"unknown policy {policy!r}; known: {', '.join(BASELINES)}")
        config = load_config(config_path, overrides)
        check_baseline(policy, config, "--policy")
        return baseline_target(policy, config, config.eval.seed if seed is None else seed)
    if target is None:
        raise TargetError(
            "give a run folder or model zip, or --policy BASELINE --config FILE (BASELINE: "
            f"{', '.join(BASELINES)})"
        )
    if config_path is not None:
        raise TargetError("--config goes with --policy; a model uses its run's config.yaml")
    return load_model_target(target, overrides, seed)


def baseline_target(policy: str, config: ExperimentConfig, seed: int) -> Target:
    """The (checked) baseline ``policy`` on ``config``'s episodes from ``seed``, with the env
    config it plays (:meth:`~harness.evaluation.baselines.BaselineEntry.env_config`: the moves
    where the config's actions are goal slots)."""
    config = config.model_copy(update={"env": BASELINES[policy].env_config(config.env)})
    prior = None
    if BASELINES[policy].reads_prior and config.eval.rollout.prior is not None:
        from harness.prior.model import load_prior  # torch: only for a prior

        try:
            prior = load_prior(config.eval.rollout.prior)
        except ValueError as exc:
            raise TargetError(f"eval.rollout.prior: {exc}") from None
    return Target(make_baseline(policy, seed, config.eval, prior), config, policy, None, seed)


def check_baseline(policy: str, config: ExperimentConfig, flag: str) -> None:
    """Refuse, in one line naming ``flag``, a baseline that is unknown or cannot play
    ``config``'s env (a planner step the config's action lacks, a coverage planner on a
    PettingZoo env of one's own)."""
    if policy not in BASELINES:
        raise TargetError(f"{flag}: unknown policy {policy!r}; known: {', '.join(BASELINES)}")
    try:
        BASELINES[policy].check(config.env.frontier_options)
        offered = [name for name, entry in BASELINES.items() if entry.any_env]
        task_of(config.env).check_baseline(policy, BASELINES[policy].any_env, offered)
    except ValueError as exc:
        raise TargetError(f"{flag} {policy}: {exc}") from None


def format_summary(summary: dict[str, Any]) -> str:
    """A readable table of an evaluation's summary (its task's)."""
    return task_of_summary(summary).format_summary(summary)


def read_eval_json(run: Path, name: str = "eval") -> dict[str, Any] | None:
    """A run's ``eval.json`` (or the evaluation ``name``: see :meth:`RunDir.eval_file`), or
    ``None`` if it was not evaluated so.

    Raises:
        TargetError: when the file is there but is not an evaluation (not JSON, not an object,
            or a number missing, not a number or not finite), naming the file and the key.
    """
    files = RunDir(run)
    try:
        data = files.read_eval(name)
        path = files.eval_file(name)
    except RunDirError as exc:
        raise TargetError(str(exc)) from None
    if data is None:
        return None
    try:
        keys = task_of_summary(data).compare_keys
    except ValueError as exc:
        raise TargetError(f"{path}: {exc}") from None
    for key in keys:
        value = data.get(key)
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise TargetError(f"{path}: {key} must be a number, got {value!r}")
        if not math.isfinite(value):
            raise TargetError(f"{path}: {key} must be finite, got {value!r}")
    return data


def read_run_curves(run: Path) -> tuple[Any, Any]:
    """The training episodes' and the in-training evaluations' curves of a run folder
    (:meth:`RunDir.read_curves`; ``None`` for the evaluations of a run made without them).

    Raises:
        TargetError: naming the file and line of anything that is not a curve.
    """
    task = task_of_log(run)
    try:
        return RunDir(run).read_curves(task.episode_metric, f"{task.prefix}_median")
    except (RunDirError, ValueError, csv.Error) as exc:  # UnicodeDecodeError is a ValueError
        raise TargetError(str(exc).splitlines()[0]) from None


def task_of_log(run: Path) -> type[Task]:
    """The task of a run folder's logs (its ``episodes.csv``'s header; the coverage env's when
    it is no task's: the reader then names the mismatch)."""
    return task_of_columns(log_header(RunDir(run).episodes_csv)) or TASKS[0]


def run_label(run: Path) -> str:
    """The experiment name of a run folder (its config's ``name``)."""
    try:
        return load_config(RunDir(run).config).name
    except ConfigError:
        return run.name


#: Temperatures ``harness tune`` tries unless told otherwise: 0 is the greedy policy, the test's
#: default (``eval.temperature``), so a temperature is chosen only where it beats greedy on the
#: validation episodes (a goal policy that follows its planner lost a point at T = 0.25).
DEFAULT_TEMPERATURES = (0.0, 0.25, 0.5, 0.75, 1.0, 1.5)
#: Validation episodes per temperature in ``harness tune``.
DEFAULT_TUNE_EPISODES = 50


def choose_temperature(rows: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """The row of a temperature sweep to test with.

    :func:`harness.evaluation.episodes.selection_score` (fewest wall hits, then the highest median
    coverage) picks it; among equals, the lower temperature (the one closer to the greedy policy).
    """
    if not rows:
        raise ValueError("no temperatures to choose from")
    return max(rows, key=lambda r: (selection_score(r), -r["temperature"]))


def tune_temperature(
    target: Target, temperatures: Sequence[float], episodes: int
) -> dict[str, Any]:
    """Evaluate a trained target at each temperature on the same validation episodes.

    Every temperature sees the same maps and start cells (episode ``k`` is seeded with
    ``target.seed + k``), so the rows differ only by the test policy. Returns the rows and the
    choice of :func:`choose_temperature`.
    """
    if target.model is None:
        raise TargetError("harness tune needs a trained model, not a baseline")
    rows = []
    for temperature in temperatures:
        ev = target.config.eval
        policy = model_policy(target.model, temperature, ev.shield)
        summary = summarize(run_episodes(policy, target.config.env, episodes, target.seed))
        keys = task_of(target.config.env).tune_keys
        # (a task's optional keys, a pettingzoo env's ``groups`` and ``select``, where it has them)
        rows.append({"temperature": temperature, **{k: summary[k] for k in keys if k in summary}})
    return {
        "policy": target.label,
        "seed": target.seed,
        "episodes": episodes,
        "shield": target.config.eval.shield,
        "rows": rows,
        "chosen": choose_temperature(rows)["temperature"],
    }


def format_tune(result: dict[str, Any]) -> str:
    """A readable table of :func:`tune_temperature`'s rows, the chosen one marked."""
    lines = [
        f"policy    {result['policy']}",
        f"episodes  {result['episodes']} per temperature (seed {result['seed']})",
        "",
    ]
    if result["rows"]:
        lines += task_of_summary(result["rows"][0]).format_tune(result)
    return "\n".join(lines)


def check_training_done(run_dir: Path) -> None:
    """Refuse to change the config of a run that has training left to resume (``tune --write``
    on a model of an unfinished run, a checkpoint's or ``best_model.zip``): its checkpoints
    resume only with the config they were made with, ``eval.temperature`` included (it picks
    ``best_model.zip``), so the write would make its next ``--resume`` refuse.

    Raises:
        TargetError: naming the run and its newest checkpoint.
    """
    from harness.training.state import RunState, run_state

    # Only a run with a checkpoint to resume (an unreadable newest one too: the resume falls
    # back to the older) is held to its config; one never checkpointed starts from its config.
    status = run_state(RunDir(run_dir))
    if status.state is RunState.RESUMABLE and status.checkpoint is not None:
        raise TargetError(
            f"--write: {run_dir} has not finished training (it resumes from "
            f"{status.checkpoint.name} only with the config.yaml it was made with); tune without "
            "--write now, or with --write once the run finished; nothing was written"
        )


def write_temperature(run_dir: Path, temperature: float) -> float:
    """Store ``temperature`` as ``eval.temperature`` in a run folder's ``config.yaml``
    (atomically) and return the one it replaces."""
    path = RunDir(run_dir).config
    config = load_config(path)
    previous = config.eval.temperature
    config.eval.temperature = temperature
    atomic_write_text(path, config.to_yaml())
    return previous


def export_reference(run: Path, out: Path, model: str = "model") -> Path:
    """Copy a run's policy into a compact, self-contained folder (``runs/reference/<name>``).

    The folder holds ``config.yaml``, the run's command, ``episodes.csv`` and
    ``evaluations.csv`` (its learning curves: training episodes and test-policy evaluations),
    the ``harness tune`` sweep of the exported model as ``tune.json``, and ``model.zip`` (or
    ``best_model.zip`` with ``model="best_model"``, saved as ``model.zip``) without the
    optimizer's state and with the online network's weights standing for the target network's
    (stored once), which matter only to continue training (together two thirds of a model zip),
    and ``reference.json`` (where it came from; it marks the folder
    as a reference). ``harness eval`` and ``harness render`` work on the folder as on the run,
    with the same actions, and write their results to ``runs/evals/<name>/``.

    Raises:
        TargetError: when the run or model is missing, or ``out`` exists (never overwritten).
    """
    source = RunDir(run).model_named(model)
    if not source.is_file():
        raise TargetError(f"{source}: no such model")
    for name in (*REFERENCE_FILES, result_filename("tune", [], model)):
        RunDir(run).result(name)  # before anything is loaded: a file linked out is refused
    if out.exists():
        raise TargetError(f"{out}: already exists (a reference is never overwritten)")
    from harness.prior.evaluate import is_prior_run

    policy: Any = None
    if is_prior_run(run):  # a map prior's zip holds its weights alone: copied as it is
        from harness.prior.model import MapPrior

        try:
            MapPrior.load(source)
        except ValueError as exc:
            raise TargetError(str(exc)) from None
    else:
        check_model_zip(source, source)
        from harness.sb3.dqn import DoubleDQN, OldModelError

        try:
            policy = DoubleDQN.load(source, device="cpu")
        except OldModelError as exc:
            raise TargetError(str(exc)) from None
        except Exception as exc:  # a damaged zip raises many kinds
            raise TargetError(
                f"{source}: cannot load model ({type(exc).__name__}: {exc})"
            ) from None
        old = policy.policy.optimizer
        # SB3 (>= 2.4) optimises only the online network, not the target network.
        policy.policy.optimizer = type(old)(policy.q_net.parameters(), **old.defaults)
    check_output_file(RunDir(out).model, "--out")
    # Written into a temporary folder beside `out`, renamed into place when complete: an
    # interrupted export leaves no half-made reference.
    out.parent.mkdir(parents=True, exist_ok=True)
    final, out = out, Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        _write_reference(run, out, model, policy)
        out.rename(final)
    except BaseException:
        shutil.rmtree(out, ignore_errors=True)
        raise
    return final


def _write_reference(run: Path, out: Path, model: str, policy: Any) -> None:
    """The files of :func:`export_reference`, into the (new, empty) folder ``out``."""
    for name in REFERENCE_FILES:
        # harness tune writes tune.json for model.zip and tune-<model>.json for the others; the
        # reference keeps the sweep of the model it holds, as its tune.json.
        tune = result_filename("tune", [])
        origin = name if name != tune or model == "model" else result_filename("tune", [], model)
        source = RunDir(run).result(origin)
        if source.is_file():
            data = source.read_bytes()
            if source.suffix == ".json":
                try:  # a reference is read by others: no damaged file goes into one
                    json.loads(data)
                except ValueError:
                    raise TargetError(f"{source}: not JSON; run harness tune again") from None
            RunDir(out).result(name).write_bytes(data)
    if model != "model":
        # The run's command made model.zip too; say which of its models this folder holds.
        RunDir(out).note_command(f"exported: {model}.zip (harness export --model {model})")
    if policy is None:  # a map prior (export_reference checked it)
        RunDir(out).model.write_bytes(RunDir(run).model_named(model).read_bytes())
    else:
        buffer = io.BytesIO()
        policy.save(buffer)
        RunDir(out).model.write_bytes(_compact_target_network(buffer.getvalue()))
    RunDir(out).write_reference_marker(run, model)


def _compact_target_network(model_zip: bytes) -> bytes:
    """An SB3 model zip whose ``policy.pth`` holds the online network's tensors as the target
    network's too: torch stores a storage once however many entries name it, so the weights take
    half the room, and ``DoubleDQN.load`` reads the zip as any other (its target network a copy of
    the online one, which only continued training would tell apart)."""
    import torch

    from harness.sb3.dqn import target_as_online

    check_model_zip(model_zip, "the exported model")
    out = io.BytesIO()
    with (
        zipfile.ZipFile(io.BytesIO(model_zip)) as zin,
        zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as zout,
    ):
        for item in zin.infolist():
            data = zin.read(item.filename)
            if item.filename == "policy.pth":
                state = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
                packed = io.BytesIO()
                torch.save(target_as_online(state), packed)
                data = packed.getvalue()
            zout.writestr(item, data)
    return out.getvalue()


# ---------------------------------------------------------------------- eval, tune, compare
def evaluate(
    target: Target,
    episodes: int,
    overrides: Sequence[str],
    progress: Callable[[int], None] | None = None,
) -> tuple[dict[str, Any], Any]:
    """``harness eval``'s work: run the episodes, summarise, and save the JSON where results of
    the target go (nothing for a baseline). ``progress``: as
    :func:`~harness.evaluation.episodes.run_episodes`' own.

    Returns:
        The summary (with per-episode ``coverage`` and ``wall_hits``), the episode results, and
        the saved file (``None`` for a baseline) as the summary's ``"saved"`` entry.
    """
    out = None
    if target.results_dir is not None:  # asked before the episodes: a link out stops it now
        name = result_filename("eval", overrides, target.model_name, episodes, target.seed_changed)
        out = RunDir(target.results_dir).result(name)
    results = run_episodes(
        target.policy, target.config.env, episodes, target.seed, progress=progress
    )
    summary: dict[str, Any] = {
        "policy": target.label,
        "seed": target.seed,
        # Only a learned policy has a test temperature (eval.temperature); baselines ignore it.
        "temperature": target.config.eval.temperature if target.run_dir is not None else None,
        "shield": target.config.eval.shield if target.run_dir is not None else None,
        "overrides": list(overrides),
        "env": target.config.env.model_dump(mode="json"),
        **summarize(results),
        **_per_episode(results),
    }
    saved = None if out is None else write_json(out, summary)
    return {**summary, "saved": saved}, results


#: The config keys that make an episode what it is (its map, size, team, starts and length, and
#: the seed): ``--against-set`` may not change them, since a paired comparison is only one on the
#: same episodes (:func:`check_against_set`). Each is refused with everything below it
#: (``env.map.cave.height``) and as a key of a mapping set above it (``env={n_agents: 3}``).
#: ``env.pettingzoo`` is which PettingZoo env (one's own) is played at all.
EPISODE_KEYS = (
    "env.map",
    "env.test_maps",
    "env.map_sha256",
    "env.height",
    "env.width",
    "env.wall_fraction",
    "env.n_agents",
    "env.starts",
    "env.max_steps",
    "env.pettingzoo",
    "seed",
)


def check_against_set(against_set: Sequence[str]) -> None:
    """Refuse, in one line, an ``--against-set`` override that changes what an episode is (a
    key of :data:`EPISODE_KEYS`, below one, or a mapping above one that names it or replaces
    the section whole).

    Raises:
        ConfigError: naming the override (also for one that is no ``key.path=value``).
    """
    for text in against_set:
        try:
            keys, value = parse_override(text)
        except ConfigError as exc:
            raise ConfigError(f"--against-set: {exc}") from None
        for episode_key in (k.split(".") for k in EPISODE_KEYS):
            if _touches(keys, value, episode_key):
                raise ConfigError(
                    f"--against-set {text[:60]}: {'.'.join(episode_key)} makes the episodes, "
                    "and a comparison is only paired on the same episodes (give it to --set, "
                    "for both)"
                )


def _touches(keys: Sequence[str], value: Any, episode_key: Sequence[str]) -> bool:
    """Whether setting ``keys`` to ``value`` may change the config key ``episode_key``."""
    shared = min(len(keys), len(episode_key))
    if list(keys[:shared]) != list(episode_key[:shared]):
        return False
    node = value
    for key in episode_key[len(keys) :]:  # nothing when keys is the key or below it
        if not isinstance(node, dict):
            return True  # the section above it replaced whole
        if key not in node:
            return False
        node = node[key]
    return True


def against_config(config: ExperimentConfig, against_set: Sequence[str]) -> ExperimentConfig:
    """The config the ``--against`` baselines play: ``config`` (the target's, with its
    ``--set``s) with the ``--against-set`` overrides applied, validated as ``--set`` is;
    ``config`` itself without them.

    Raises:
        ConfigError: for an override :func:`check_against_set` refuses, or a bad key or value
            (``--set``'s own error, after ``--against-set:``).
    """
    if not against_set:
        return config
    check_against_set(against_set)
    try:
        return config_from_dict(config.model_dump(mode="json"), "the target's config", against_set)
    except ConfigError as exc:
        raise ConfigError(f"--against-set: {exc}") from None


def evaluate_against(
    target: Target,
    summary: dict[str, Any],
    policy: str,
    overrides: Sequence[str],
    progress: Callable[[int], None] | None = None,
    against_set: Sequence[str] = (),
) -> dict[str, Any]:
    """``harness eval --against POLICY``: the baseline ``policy`` on the episodes of ``target``'s
    evaluation ``summary`` (:func:`evaluate`: the same maps and starts, from the same seed), and
    the two compared episode by episode on coverage (a PettingZoo env of one's own: the team
    return): the mean difference with its 95 % percentile-bootstrap interval over the episodes
    (:func:`~harness.results.stats.paired_difference`) and the episodes each is ahead in. Saved
    beside the evaluation (:func:`~harness.results.rundir.against_filename`; nothing for a
    baseline target), with both per-episode lists.

    ``progress``: as :func:`evaluate`'s, for the baseline's episodes. ``against_set``: the
    ``--against-set`` overrides the baseline alone plays under (:func:`against_config`, on the
    same episodes); named in the comparison (``"against_set"``) and its file's name.

    Returns:
        The comparison, with the saved file (or ``None``) as its ``"saved"`` entry.
    """
    from harness.results.stats import paired_difference

    episodes = summary["episodes"]
    out = None
    if target.results_dir is not None:  # asked before the episodes: a link out stops it now
        name = against_filename(
            policy, overrides, target.model_name, episodes, target.seed_changed, against_set
        )
        out = RunDir(target.results_dir).result(name)
    baseline = baseline_target(policy, against_config(target.config, against_set), target.seed)
    results = run_episodes(
        baseline.policy, baseline.config.env, episodes, target.seed, progress=progress
    )
    theirs = _per_episode(results)
    metric = task_of(baseline.config.env).episode_metric
    a = np.asarray(summary[metric], dtype=np.float64)
    b = np.asarray(theirs[metric], dtype=np.float64)
    difference, low, high = paired_difference(a, b)
    comparison: dict[str, Any] = {
        "policy": target.label,
        "against": policy,
        "seed": target.seed,
        "episodes": episodes,
        "overrides": list(overrides),
        # Only where given: a plain comparison's file stays as it was.
        **({"against_set": list(against_set)} if against_set else {}),
        "metric": metric,
        "mean": float(a.mean()),
        "against_mean": float(b.mean()),
        "difference": difference,
        "difference_ci95": [low, high],
        "ahead": int((a > b).sum()),
        "behind": int((a < b).sum()),
        "equal": int((a == b).sum()),
        metric: a.tolist(),
        f"against_{metric}": b.tolist(),
    }
    if metric == "coverage":
        ours_steps, their_steps = summary["steps_to_99_each"], theirs["steps_to_99_each"]
        comparison["steps_to_99"] = paired_steps_to_99(ours_steps, their_steps)
        comparison["steps_to_99_each"] = ours_steps
        comparison["against_steps_to_99_each"] = their_steps
    saved = None if out is None else write_json(out, comparison)
    return {**comparison, "saved": saved}


def paired_steps_to_99(
    ours: Sequence[int | None], theirs: Sequence[int | None]
) -> dict[str, Any] | None:
    """The steps to 99 % of two policies compared on the episodes both reach it in (where teams
    cover everything, coverage ties and speed is the measure): their means, the mean
    difference (ours - theirs: negative is faster) with its 95 % bootstrap interval; ``None``
    when no episode is reached by both."""
    from harness.results.stats import paired_difference

    pairs = [(x, y) for x, y in zip(ours, theirs, strict=True) if x is not None and y is not None]
    if not pairs:
        return None
    a, b = np.asarray(pairs, dtype=np.float64).T
    difference, low, high = paired_difference(a, b)
    return {
        "episodes": len(pairs),
        "mean": float(a.mean()),
        "against_mean": float(b.mean()),
        "difference": difference,
        "difference_ci95": [low, high],
    }


def _against_name(comparison: dict[str, Any]) -> str:
    """The baseline of a comparison as its lines name it, with the ``--against-set`` overrides
    it played under."""
    sets = comparison.get("against_set") or []
    return comparison["against"] + "".join(f" --against-set {text}" for text in sets)


def format_against(comparison: dict[str, Any]) -> str:
    """One line of :func:`evaluate_against`'s comparison."""
    from harness.results.stats import plain

    coverage = comparison["metric"] == "coverage"
    value = "{:.1%}".format if coverage else plain
    low, high = comparison["difference_ci95"]

    def diff(x: float) -> str:  # coverage in points (of 100)
        return f"{100 * x:+.2f}" if coverage else f"{x:+.4g}"

    unit = " points" if coverage else ""
    what = "coverage" if coverage else "team return"
    line = (
        f"against   {_against_name(comparison)} on the same {comparison['episodes']} episodes: "
        f"mean {what} {value(comparison['against_mean'])} (this policy "
        f"{value(comparison['mean'])}), difference {diff(comparison['difference'])}{unit} "
        f"[{diff(low)}, {diff(high)}] (95 % bootstrap over the episodes); this policy ahead in "
        f"{comparison['ahead']}, behind in {comparison['behind']}, equal in {comparison['equal']}"
    )
    steps = comparison.get("steps_to_99")
    if steps is not None:
        low, high = steps["difference_ci95"]
        line += (
            f"\n          steps to 99 %, on the {steps['episodes']} episodes both reach it in: "
            f"mean {steps['against_mean']:.1f} (this policy {steps['mean']:.1f}), difference "
            f"{steps['difference']:+.1f} [{low:+.1f}, {high:+.1f}]"
        )
    return line


def format_group_against(comparison: dict[str, Any]) -> str:
    """One line of :func:`group_against`'s differences over seeds."""
    from harness.results.stats import with_ci

    over = comparison["difference_over_seeds"]
    coverage = comparison["metric"] == "coverage"

    def diff(x: float) -> str:  # coverage in points (of 100)
        return f"{100 * x:+.2f}" if coverage else f"{x:+.4g}"

    what = "points of coverage" if coverage else "team return"
    line = (
        f"== over {over['seeds']} seeds against {_against_name(comparison)} (paired on each run's "
        f"episodes), mean difference ({what}) {with_ci(over['mean'], over['mean_ci95'], diff)}, "
        f"IQM {with_ci(over['iqm'], over['iqm_ci95'], diff)}"
    )
    steps = comparison.get("steps_to_99_difference_over_seeds")
    if steps is not None:
        step_diff = "{:+.1f}".format
        line += (
            "\n   steps to 99 % (each run's on the episodes both reach it in), mean difference "
            f"{with_ci(steps['mean'], steps['mean_ci95'], step_diff)}, IQM "
            f"{with_ci(steps['iqm'], steps['iqm_ci95'], step_diff)}"
        )
    return line


def _per_episode(results: list[Any]) -> dict[str, list[Any]]:
    """The per-episode numbers an evaluation keeps (its task's: coverage, wall hits and steps to
    99 % for the coverage env; team return and length for a PettingZoo env)."""
    return type(results[0]).task.per_episode(results) if results else {}


#: The per-episode lists of :func:`evaluate` that ``--json`` leaves out (the file keeps them).
PER_EPISODE_KEYS = ("coverage", "wall_hits", "steps_to_99_each", "team_return", "length")


def format_over_seeds(result: dict[str, Any]) -> str:
    """The line of ``group-eval.json``'s numbers over seeds (its task's headline, the mean with
    its 95 % interval and the IQM): ``== over 3 seeds: mean coverage ...``."""
    from harness.results.stats import percent, plain, with_ci

    for task in TASKS:
        over = result.get(f"{task.prefix}_mean_over_seeds")
        if over is not None:
            fmt = percent if task.percent else plain
            return (
                f"== over {over['seeds']} seeds: mean {task.metric} "
                f"{with_ci(over['mean'], over['mean_ci95'], fmt)}, "
                f"IQM {with_ci(over['iqm'], over['iqm_ci95'], fmt)}"
            )
    raise ValueError("no numbers over seeds in this group evaluation")


def evaluate_group(
    group: Path,
    evaluate_run: Callable[[Path], object],
    against: Sequence[str] = (),
    episodes: int = STANDARD_EPISODES,
    overrides: Sequence[str] = (),
    seed: int | None = None,
    against_set: Sequence[str] = (),
) -> tuple[dict[str, Any] | None, Path | None, list[str]]:
    """``harness eval GROUP``: ``evaluate_run(run)`` for every run (``harness eval RUN`` with
    ``episodes``, ``overrides`` and ``seed``), then the numbers over seeds of the evaluation
    each run saved, in the group's file named after it
    (:func:`~harness.results.groups.group_result_file`): ``GROUP/group-eval.json`` for the
    standard evaluation (each run's ``eval.json``), ``GROUP/group-eval-30ep.json`` for
    ``--episodes 30`` (each run's ``eval-30ep.json``), so that no evaluation of the group
    replaces another's numbers. None when a seed's run is missing (their names are returned:
    numbers over the others would read as the group's). With ``against`` (baselines
    ``evaluate_run`` also compared each run with: :func:`evaluate_against`), each baseline's
    paired differences over seeds too (:func:`group_against`: ``GROUP/group-against-BASELINE.json``,
    ``GROUP/group-against-BASELINE-30ep.json``), listed under the result's ``"against"``; the
    baselines played under ``against_set`` (``--against-set``) where given.

    Raises:
        GroupError: when the runs would save the evaluation under different names (``seed``
            against configs with different ``eval.seed``s: no one file holds them).
    """
    from harness.results.groups import group_file, group_members, group_result_file, group_runs
    from harness.results.stats import describe, seed_statistics

    runs = group_runs(group)
    missing = [run.name for run in group_members(group) if run not in runs]
    eval_name, against_names = _group_run_files(
        group, runs, against, episodes, overrides, seed, against_set
    )
    out = group_file(group, group_result_file(eval_name))  # asked before the runs are evaluated
    summaries = {}
    for run in runs:
        evaluate_run(run)
        data = read_eval_json(run, eval_name.removesuffix(".json"))
        if data is not None:
            summaries[run.name] = data
    if missing or len(summaries) != len(runs):
        return None, None, missing
    stats = seed_statistics({"group": [headline(s, "mean") for s in summaries.values()]})
    task = task_of_summary(next(iter(summaries.values())))
    keys, over = task.group_keys, f"{task.prefix}_mean_over_seeds"
    result: dict[str, Any] = {
        "group": str(group),
        "runs": {name: {k: s[k] for k in keys} for name, s in summaries.items()},
        over: describe(stats["group"]),
    }
    saved = write_json(out, result)
    if against:
        result["against"] = [
            group_against(group, runs, policy, against_names[policy], against_set)
            for policy in against
        ]
    return result, saved, []


def _group_run_files(
    group: Path,
    runs: Sequence[Path],
    against: Sequence[str],
    episodes: int,
    overrides: Sequence[str],
    seed: int | None,
    against_set: Sequence[str] = (),
) -> tuple[str, dict[str, str]]:
    """The file each of ``runs`` saves ``harness eval RUN`` with ``episodes``, ``overrides`` and
    ``seed`` as (:func:`evaluate`: its ``model.zip``, :func:`result_filename`), and each
    baseline's comparison (:func:`evaluate_against`: :func:`against_filename`), the same for
    every run. A seed names the files only where it is not the run's ``eval.seed`` (as
    :attr:`Target.seed_changed`), so its config is read only for one.

    Raises:
        GroupError: when two runs name them differently (configs with different ``eval.seed``).
    """
    from harness.results.groups import GroupError

    names: dict[tuple[str, tuple[str, ...]], list[str]] = {}
    for run in runs:
        changed = None
        if seed is not None and seed != load_config(RunDir(run).config, overrides).eval.seed:
            changed = str(seed)
        files = (
            result_filename("eval", overrides, "model", episodes, changed),
            tuple(
                against_filename(p, overrides, "model", episodes, changed, against_set)
                for p in against
            ),
        )
        names.setdefault(files, []).append(run.name)
    if len(names) > 1:
        (first, *_), (second, *_) = list(names.values())[:2]
        raise GroupError(
            f"{group}: --seed {seed} is the eval.seed of some runs' configs but not of others "
            f"({first}, {second}): their evaluations are saved under different names; evaluate "
            "the runs one by one"
        )
    (eval_name, against_names), *_ = names
    return eval_name, dict(zip(against, against_names, strict=True))


def group_against(
    group: Path,
    runs: Sequence[Path],
    policy: str,
    run_file: str | None = None,
    against_set: Sequence[str] = (),
) -> dict[str, Any]:
    """The runs' paired differences from the baseline ``policy`` on their test episodes (each
    run's comparison ``run_file``, by default the standard evaluation's ``against-POLICY.json``:
    :func:`evaluate_against`) over seeds: mean and IQM with rliable's 95 % intervals over the
    seeds' differences (one run: no interval), saved in the group's file named after
    ``run_file`` (:func:`~harness.results.groups.group_result_file`:
    ``GROUP/group-against-POLICY.json``, ``GROUP/group-against-POLICY-30ep.json``). The question
    it answers is the training's: does a seed of this training beat the baseline on the same
    episodes, and by how much? ``against_set``: the ``--against-set`` overrides the baseline
    played under (their ``run_file`` names them), said in the result."""
    from harness.results.groups import group_file, group_result_file
    from harness.results.stats import describe, seed_statistics

    if run_file is None:
        run_file = against_filename(policy, [], against_set=against_set)
    differences: dict[str, float] = {}
    steps: dict[str, float] = {}  # the steps to 99 %, of the runs that have a comparison of them
    metric = "coverage"
    for run in runs:
        path = RunDir(results_folder(run)).result(run_file)
        data = json.loads(path.read_text(encoding="utf-8"))  # written by this command
        differences[run.name], metric = float(data["difference"]), data["metric"]
        if data.get("steps_to_99") is not None:
            steps[run.name] = float(data["steps_to_99"]["difference"])
    stats = seed_statistics({policy: list(differences.values())})[policy]
    result: dict[str, Any] = {
        "group": str(group),
        "against": policy,
        **({"against_set": list(against_set)} if against_set else {}),
        "metric": metric,
        "differences": differences,
        "difference_over_seeds": describe(stats),
    }
    if steps and len(steps) == len(runs):  # over seeds only where every seed has one
        result["steps_to_99_differences"] = steps
        over = seed_statistics({policy: list(steps.values())})[policy]
        result["steps_to_99_difference_over_seeds"] = describe(over)
    saved = write_json(group_file(group, group_result_file(run_file)), result)
    return {**result, "saved": saved}


def tune(
    target: Target,
    temperatures: Sequence[float],
    episodes: int,
    overrides: Sequence[str],
    write: bool,
) -> tuple[dict[str, Any], Path]:
    """``harness tune``'s work: the sweep on validation episodes, optionally written into the run's
    config as its test temperature, saved as ``tune*.json`` where the target's results go.

    Raises:
        TargetError: for ``write`` on a reference, or with ``--set`` overrides.
    """
    assert target.run_dir is not None and target.results_dir is not None  # a trained model
    if write and overrides:
        raise TargetError("--write stores a choice for the run's own config; drop --set")
    if write and is_reference(target.run_dir):
        raise TargetError(
            f"{target.run_dir}: a reference is read-only; --write tunes a run folder's config"
        )
    if write:
        check_training_done(target.run_dir)
    # tune.json, or tune-best_model.json, tune-env.max_steps-500.json, ... like harness eval's;
    # asked before the episodes: a link out of the folder stops it now.
    out = RunDir(target.results_dir).result(result_filename("tune", overrides, target.model_name))
    result = tune_temperature(target, temperatures, episodes)
    result["overrides"] = list(overrides)
    if write:
        result["previous_temperature"] = write_temperature(target.run_dir, result["chosen"])
    return result, write_json(out, result)


def render(target: Target, out: Path | None, gif: Path | None, every: int | None) -> list[Path]:
    """``harness render``'s work: episode 0 of the target's seed as a path picture (``out``, by
    default ``paths.png`` where the target's results go) and, with ``gif``, an animated GIF
    (:func:`harness.results.plots.gif_frames`) keeping a frame every ``every`` steps (``None``:
    :func:`harness.results.plots.gif_every` of the episode's length). Returns the files written.

    Raises:
        TargetError: for a GIF whose frames would take more than
            :data:`harness.results.plots.MAX_GIF_BYTES` of memory, before the episode is played.
    """
    from harness.results import plots

    env = target.config.env
    note = sampling_note(target.config.eval.temperature) if target.run_dir else ""
    task = task_of(env)
    if not task.paths:  # no path picture: the env's own frames
        return _render_frames(target, out, gif, every or task.render_every)
    # Asked before the episode: a paths.png linked out of the folder stops it now.
    out = out or RunDir(target.results_dir or Path()).paths_png
    if gif is not None:
        every = every or plots.gif_every(env.max_steps)
        largest = make_env(env)  # before its first reset: the largest map its source makes
        widest = plots.gif_title(target.label, target.seed, 1.0, note)  # "100.0%"
        need, per_frame = plots.gif_bytes(
            (largest.height, largest.width), env.n_agents, env.max_steps, every, widest
        )
        limit = plots.MAX_GIF_BYTES
        if need > limit:
            fit = limit // per_frame  # frames that fit: step 0 and one every ``every`` steps
            advice = (
                f"use --every {math.ceil(env.max_steps / (fit - 1))} or more"
                if fit >= 2
                else "a smaller map or no --gif"
            )
            raise TargetError(
                f"--gif {gif}: {need // per_frame:,} frames of a {largest.height}-row, "
                f"{largest.width}-column map (one every {every} of {env.max_steps} steps) "
                f"need about {plots.byte_size(need)} of memory, over the "
                f"{plots.byte_size(limit)} limit; {advice}"
            )
    rec = plots.play_episode(env, target.policy, target.seed, every or 1, gif is not None)
    title = f"{target.label}: coverage {rec.coverage:.1%}, seed {target.seed}"
    title += f", {note}" if note else ""
    saved = [plots.plot_paths(rec.walls, rec.paths, out, title)]
    if gif is not None:
        assert every is not None
        frames = plots.gif_frames(
            rec, every, plots.gif_title(target.label, target.seed, rec.coverage, note)
        )
        rec.frames = []  # the env's frames: not needed any more
        saved.append(
            plots.write_gif(
                frames, gif, plots.GIF_FPS, hold=plots.GIF_HOLD, palette=plots.gif_palette()
            )
        )
    return saved


def _render_frames(
    target: Target, out: Path | None, gif: Path | None, every: int | None
) -> list[Path]:
    """``harness render`` of a task without paths (a PettingZoo env): episode 0 of the target's seed
    played with the env's ``rgb_array`` frames; its last frame as ``out`` (by default
    ``render.png`` where the target's results go) and, with ``gif``, every ``every``-th frame
    as an animated GIF. No path picture: paths are the coverage env's. The frames a GIF keeps
    are bounded by :data:`harness.results.plots.MAX_GIF_BYTES`, measured from the first frame
    (the env's frames can be of any size); without a GIF only the first and last are kept.

    Raises:
        TargetError: when the env does not render ``rgb_array`` frames, or when the GIF's frames
            would take more than that memory.
    """
    from PIL import Image

    from harness.results import plots

    env = target.config.env
    try:
        task_of(env).check_renders()
    except ValueError as exc:
        raise TargetError(f"render: {exc}") from None
    every = every or 1
    out = out or RunDir(target.results_dir or Path()).result("render.png")  # asked first
    try:
        (result,) = run_episodes(
            target.policy,
            env,
            1,
            target.seed,
            copies=1,
            # No GIF: the last frame alone is wanted (with the first, which costs one frame).
            frames_every=every if gif is not None else sys.maxsize,
            frame_bytes=plots.MAX_GIF_BYTES,
        )
    except TooManyFrames as exc:
        raise TargetError(
            f"--gif {gif}: {exc}: keep fewer with a larger --every, or no --gif"
            if gif is not None
            else f"render: {exc}"
        ) from None
    frames = [np.asarray(frame, dtype=np.uint8) for frame in result.frames]
    last = Image.fromarray(frames[-1])
    atomic_write(out, lambda tmp: last.save(tmp, format="PNG"))  # whole or not at all
    saved = [out]
    if gif is not None:
        saved.append(plots.write_gif(frames, gif, plots.GIF_FPS, hold=plots.GIF_HOLD))
    return saved


def _mixed(tasks: set[type[Any]]) -> str:
    """Tasks that do not compare: ``coverage (coverage) and pettingzoo (team return)``."""
    return " and ".join(sorted(f"{task.name} ({task.metric})" for task in tasks))


@dataclass
class Comparison:
    """What ``harness compare`` found: per-run rows, the over-seeds table and the files made."""

    rows: list[tuple[str, str, dict[str, Any] | None]]
    over_seeds: str
    saved: list[Path]
    #: Per run without the evaluation asked for: the evaluations it has (``--eval`` stems).
    others: dict[str, list[str]] = dataclasses.field(default_factory=dict)
    #: Per row: the evaluation it read (its stem: ``eval``, ``eval-20ep``), ``None`` for none.
    used: list[str | None] = dataclasses.field(default_factory=list)


def compare(
    items: Sequence[Path],
    labels: Sequence[str | None],
    out: Path,
    window: int,
    reps: int,
    eval_name: str | None = None,
) -> Comparison:
    """``harness compare``'s work: learning curves of runs and seed groups, each run's test
    numbers (the evaluation ``eval_name``; ``None``: :func:`default_eval`'s), and over the seeds
    of each group the mean and IQM with 95 % bootstrap intervals and the probability of
    improvement (rliable, ``reps`` bootstrap resamples)."""
    from harness.results.groups import group_runs, is_group
    from harness.results.plots import plot_learning_curves

    check_output_file(out, "--out")
    for picture in compare_pictures(out):  # made beside --out, never through a link out
        inside(picture, out.parent, "the folder of --out")
    curves: dict[str, list[Any]] = {}
    evaluations: dict[str, list[Any]] = {}
    rows: list[tuple[str, str, dict[str, Any] | None]] = []
    others: dict[str, list[str]] = {}
    used: list[str | None] = []
    taken: dict[str, int] = {}
    seen: dict[Path, Path] = {}
    from harness.prior.evaluate import is_prior_run

    for item in items:  # a run counted twice would narrow every interval over seeds
        for run in group_runs(item) if is_group(item) else [item]:
            if is_prior_run(run):  # its curves are TensorBoard's, its score harness eval's
                raise TargetError(
                    f"{run} is a map prior's run: its training curves are TensorBoard's "
                    f"(tensorboard --logdir RUN), its score harness eval {run} --json"
                )
            key = Path(run).resolve()
            if key in seen:
                raise TargetError(f"{run} is compared twice (also in {seen[key]}): name it once")
            seen[key] = Path(item)
    for item, given in zip(items, labels, strict=True):
        runs = group_runs(item) if is_group(item) else [item]
        label = given or run_label(runs[0] if runs else item)
        if not given and is_group(item):
            # Two groups of one config (say, two --set variants) stay apart: name#2, name#3;
            # runs named one by one share their config's label (the seeds of one experiment).
            taken[label] = taken.get(label, 0) + 1
            label = label if taken[label] == 1 else f"{label}#{taken[label]}"
        for run in runs:
            episodes, evals = read_run_curves(run)
            curves.setdefault(label, []).append(episodes)
            if evals is not None:
                evaluations.setdefault(label, []).append(evals)
            name = default_eval(run) if eval_name is None else eval_name
            found = None if name is None else read_eval_json(run, name)
            rows.append((label, run.name, found))
            used.append(name if found is not None else None)
            if found is None:
                others[run.name] = RunDir(run).eval_names()
    tasks = {task_of_log(run) for run in seen}
    if len(tasks) > 1:
        raise TargetError(f"compare: these runs mix tasks: {_mixed(tasks)}, which do not compare")
    task = tasks.pop() if tasks else None
    metric = None if task is None or task.percent else task.metric
    title = f"{metric or 'team coverage'} of the training episodes"
    boundaries = sorted({b for run in seen for b in phase_boundaries(run)})
    saved = [
        plot_learning_curves(
            curves,
            out,
            title,
            window=window,
            evaluations=evaluations,
            metric=metric,
            boundaries=boundaries,
        )
    ]
    over_seeds, more = _over_seeds(rows, evaluations, Path(out), reps, used, boundaries)
    return Comparison(rows, over_seeds, saved + more, others, used)


def phase_boundaries(run: Path) -> list[int]:
    """The transitions at which a run's training phases end, but the last (its config's phases'
    ``timesteps`` summed): where compare draws a dotted line. None for a run whose config does
    not load (its curves are still drawn)."""
    try:
        phases = load_config(RunDir(run).config).phases
    except ConfigError:
        return []
    ends = itertools.accumulate(phase.timesteps for phase in phases)
    return list(ends)[:-1]


def default_eval(run: Path) -> str | None:
    """The evaluation ``compare`` reads of a run when ``--eval`` does not say: ``eval``
    (``eval.json``, the standard one), else the run's only other one (``eval-20ep`` after
    ``harness eval RUN --episodes 20``); ``None`` for none, or several others (which one is
    the user's choice: compare lists them)."""
    names = RunDir(run).eval_names()
    if "eval" in names:
        return "eval"
    return names[0] if len(names) == 1 else None


def compare_pictures(out: Path) -> tuple[Path, Path, Path]:
    """The pictures ``harness compare --out OUT.png`` makes beside ``OUT.png``: the test numbers'
    intervals, the probabilities of improvement and the validation curves with their intervals
    (``OUT-intervals.png``, ``OUT-improvement.png``, ``OUT-curves-ci.png``)."""
    intervals, improvement, curves = (
        out.with_name(f"{out.stem}-{kind}.png")
        for kind in ("intervals", "improvement", "curves-ci")
    )
    return intervals, improvement, curves


def _over_seeds(
    rows: list[tuple[str, str, dict[str, Any] | None]],
    evaluations: dict[str, list[Any]],
    out: Path,
    reps: int,
    used: Sequence[str | None],
    boundaries: Sequence[float] = (),
) -> tuple[str, list[Path]]:
    """The over-seeds part of ``compare``: a Markdown table, P(X > Y) per pair, two PNGs.
    ``used``: per row, the evaluation it read (``Comparison.used``)."""
    from harness.results.stats import (
        CONCLUSIVE_SEEDS,
        group_colours,
        markdown_table,
        percent,
        plain,
        plot_curves_with_ci,
        plot_improvement,
        plot_intervals,
        probability_of_improvement,
        seed_statistics,
    )

    scores: dict[str, list[float]] = {}
    hits: dict[str, list[float]] = {}
    found = [ev for _, _, ev in rows if ev is not None]
    tasks = {task_of_summary(ev) for ev in found}
    if len(tasks) > 1:
        raise TargetError(
            f"compare: these runs' evaluations mix tasks: {_mixed(tasks)}, which do not compare"
        )
    if not tasks:
        return "", []
    task = tasks.pop()
    for label, _, ev in rows:
        if ev is not None:
            scores.setdefault(label, []).append(task.headline(ev, "mean"))
            if task.penalty is not None:
                hits.setdefault(label, []).append(float(ev[task.penalty]))
    stats = seed_statistics(scores, reps)
    if task.percent:  # a fraction, in percent, with its penalty (the coverage env's wall hits)
        metric, fmt, scale, unit = f"test {task.metric}", percent, 100.0, ""
        table = markdown_table(stats, {k: sum(v) / len(v) for k, v in hits.items()})
    else:  # a plain number (a PettingZoo env's team return)
        metric, fmt, scale, unit = f"test {task.metric}", plain, 1.0, task.metric
        table = markdown_table(stats, None, metric, fmt)
    # Some run has an evaluation here (scores): each one read is named.
    files = [f"{name}.json" for name in dict.fromkeys(n for n in used if n)]
    over = (
        f"each seed's mean over its {files[0]} episodes"
        if len(files) == 1  # runs evaluated differently are named: --eval makes them one
        else f"each seed's mean over its own evaluation: {', '.join(files)}; --eval NAME for one"
    )
    lines = [
        f"Over seeds: {metric} ({over})",
        "",
        table,
    ]
    names = list(scores)
    pairs = {}
    for i, x in enumerate(names):
        for y in names[i + 1 :]:
            if len(scores[x]) == len(scores[y]) == 1:
                # One number against one: 0, 50 or 100 % would read as a probability.
                lines += ["", f"P({x} > {y}): not estimated (one seed in each group)"]
                continue
            p, ci = probability_of_improvement(scores[x], scores[y], reps)
            where = (
                "no interval: a group has 1 seed"
                if ci is None
                else f"95 % CI [{percent(ci[0])}, {percent(ci[1])}]"
            )
            if ci is not None and min(len(scores[x]), len(scores[y])) < CONCLUSIVE_SEEDS:
                where += f"; not conclusive: a group has under {CONCLUSIVE_SEEDS} seeds"
            lines += ["", f"P({x} > {y}) = {percent(p)} ({where})"]
            if ci is not None:
                pairs[x, y] = (p, ci)
    # One colour per group across every figure of this comparison.
    colours = group_colours(list(dict.fromkeys([*names, *evaluations])))
    intervals_png, improvement_png, curves_png = compare_pictures(out)
    if unit:
        xlabel = f"test {unit}, 95 % stratified-bootstrap CIs"
        saved = [plot_intervals(stats, intervals_png, colours, xlabel, scale)]
    else:
        saved = [plot_intervals(stats, intervals_png, colours)]
    if pairs:
        saved.append(plot_improvement(pairs, improvement_png))
    if evaluations:
        if unit:
            ylabel = f"validation median {unit}, IQM"
            saved.append(
                plot_curves_with_ci(
                    evaluations, curves_png, reps, colours, ylabel, 1.0, boundaries=boundaries
                )
            )
        else:
            saved.append(
                plot_curves_with_ci(evaluations, curves_png, reps, colours, boundaries=boundaries)
            )
    return "\n".join(lines), saved
