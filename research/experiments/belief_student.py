"""A student of the sampled-map chooser (research/experiment-log.md, "A chooser that sees only the
team's map"): a goal policy fitted offline to the decisions that ``goal_oracle.py --belief
sampled --save`` recorded, played back with ``goal_oracle.py --model``.

The network is the config's (``SlotTeamMapPolicy``, built as ``harness run`` builds it); its
Q-values over the candidate slots are read as logits and fitted by cross-entropy to the
chooser's slot, a deviation from slot 0 weighted ``--deviation-weight`` times (they are a few
per cent of the labels); or, with ``--target gain``, regressed on each slot's mean gain over
the sampled maps (in steps, clipped to ``--clip``, less ``--margin-steps`` for every slot but
0, so that the greedy choice leaves slot 0 only where the predicted gain exceeds that margin).
Decisions at a coverage of ``--below`` (99 %) or more are left out: after it no choice moves
the steps to 99 %. The decisions of the last ``--held-out`` episodes are kept out of the fit
and report the student's agreement: on every decision, on the chooser's deviations (recall)
and on the student's own (precision); ``--fit-episodes N`` fits on the first ``N`` episodes
only (a learning curve over the labels). ``--student features`` fits, instead of the network,
an MLP that scores each slot from its candidate features beside slot 0's alone (no team map):
how much of the choice the candidates' features tell; it is reported, not saved.

    python research/experiments/belief_student.py DATA.npz [DATA.npz ...] [--out student.zip]
        [--student network|features] [--config configs/goals_4agents.yaml] [--epochs 30]
        [--deviation-weight 10] [--held-out 2] [--fit-episodes N] [--below 0.99]
        [--target label|gain] [--margin-steps 2] [--seed 0]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from scipy.stats import mannwhitneyu

from envs.coverage.goals import ACTION_MASK_KEY, GOALS_KEY
from harness.config.loading import load_config
from harness.training.adapters import make_vec_env
from harness.training.train import build_model


def load(
    paths: list[Path], below: float, unit: float
) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray, np.ndarray]:
    """The observations (key by key), labels, episode numbers and slot gains (in steps: score
    units over each decision's saved ``unit``, or over ``unit`` for files saved without one) of
    every file's decisions at a coverage below ``below``, the episodes numbered across files."""
    obs: dict[str, list[np.ndarray]] = {}
    labels, episodes, gains, first = [], [], [], 0
    for path in paths:
        data = np.load(path)
        keep = data["coverage"] < below
        for key in data.files:
            if key.startswith("obs_"):
                obs.setdefault(key[4:], []).append(data[key][keep])
        labels.append(data["label"][keep])
        units = data["unit"][keep] if "unit" in data.files else np.full(keep.sum(), unit)
        gains.append(
            data["gain"][keep] / units[:, None]
            if "gain" in data.files
            else np.full(data["advantages"][keep].shape, np.nan)
        )
        episodes.append(data["episode"][keep] + first)
        first += int(data["episode"].max()) + 1
    return (
        {k: np.concatenate(v) for k, v in obs.items()},
        np.concatenate(labels),
        np.concatenate(episodes),
        np.concatenate(gains),
    )


def report(name: str, q: np.ndarray, label: np.ndarray) -> None:
    """Agreement of the greedy slot of ``q`` (masked Q-values) with the chooser's ``label``,
    and the AUC of the best other slot's lead over slot 0 as a score of the chooser's
    deviations (0.5: no better than chance)."""
    pred = q.argmax(1)
    agree = (pred == label).mean()
    dev = label != 0
    recall = (pred[dev] == label[dev]).mean() if dev.any() else float("nan")
    own = pred != 0
    precision = (pred[own] == label[own]).mean() if own.any() else float("nan")
    lead = q[:, 1:].max(1) - q[:, 0]
    auc = float("nan")
    if dev.any() and (~dev).any():
        auc = mannwhitneyu(lead[dev], lead[~dev]).statistic / (dev.sum() * (~dev).sum())
    print(
        f"{name}: {label.size} decisions, agreement {100 * agree:.1f} %; chooser's deviations "
        f"{dev.sum()}, taken {100 * recall:.1f} % (AUC of the lead over slot 0 {auc:.3f}); "
        f"student's {own.sum()}, agreed {100 * precision:.1f} %"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("data", type=Path, nargs="+")
    parser.add_argument("--out", type=Path, help="save the student (--student network) here")
    parser.add_argument(
        "--student",
        choices=("network", "features"),
        default="network",
        help="the config's goal network (team map and candidates), or an MLP over each "
        "candidate's features beside slot 0's alone (no team map; not saved)",
    )
    parser.add_argument("--config", default="configs/goals_4agents.yaml")
    parser.add_argument("--epochs", type=int, default=30)
    parser.add_argument("--batch", type=int, default=256)
    parser.add_argument("--lr", type=float, default=3e-4)
    parser.add_argument("--deviation-weight", type=float, default=10.0)
    parser.add_argument(
        "--target",
        choices=("label", "gain"),
        default="label",
        help="fit the chooser's slot (cross-entropy) or each slot's mean gain (regression)",
    )
    parser.add_argument(
        "--margin-steps",
        type=float,
        default=2.0,
        help="with --target gain: steps (cells, for files scored by cells) a slot must gain "
        "over slot 0 to be the greedy choice",
    )
    parser.add_argument("--clip", type=float, default=20.0, help="gain targets clipped, steps")
    parser.add_argument(
        "--unit",
        type=float,
        default=2705.0,
        help="score units a step of files saved without their own (50x50: 52 * 52 + 1)",
    )
    parser.add_argument("--held-out", type=int, default=2, help="last episodes kept out")
    parser.add_argument(
        "--fit-episodes",
        type=int,
        default=None,
        help="fit on the first N episodes only (a learning curve over the labels; default: all "
        "but the held-out ones)",
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--below",
        type=float,
        default=0.99,
        help="fit the decisions below this coverage (after 99 %% no choice moves the steps to it)",
    )
    args = parser.parse_args()
    if args.out is not None and args.student == "features":
        parser.error("--out saves a goal policy: only with --student network")

    torch.manual_seed(args.seed)
    config = load_config(args.config, ["env.map=random"])
    obs, labels, episodes, gains = load(args.data, args.below, args.unit)
    cut = episodes.max() - args.held_out + 1
    fit, held = episodes < cut, episodes >= cut
    if args.fit_episodes is not None:
        fit &= episodes < args.fit_episodes
    print(
        f"{labels.size} decisions of {episodes.max() + 1} episodes; fitted on {fit.sum()} "
        f"({(labels[fit] != 0).sum()} deviations), held out {held.sum()}"
    )
    tensors = {k: torch.as_tensor(v) for k, v in obs.items()}
    target = torch.as_tensor(labels)

    if args.student == "features":
        # Each slot scored from its candidate features beside slot 0's, one MLP shared by the
        # slots: what the candidates' own features tell, without the team map.
        width = tensors[GOALS_KEY].shape[-1]
        scorer = torch.nn.Sequential(
            torch.nn.Linear(2 * width, 64),
            torch.nn.ReLU(),
            torch.nn.Linear(64, 64),
            torch.nn.ReLU(),
            torch.nn.Linear(64, 1),
        )

        def scores(index: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            goals = tensors[GOALS_KEY][index].float()
            pairs = torch.cat([goals, goals[:, :1].expand_as(goals)], dim=-1)
            return scorer(pairs).squeeze(-1), tensors[ACTION_MASK_KEY][index].bool()

        weights = scorer.parameters()
        device = torch.device("cpu")
    else:
        venv = make_vec_env(config.env, copies=1, seed=0)
        model = build_model(config, venv)  # only the network student: built where it is fitted
        venv.close()
        policy = model.policy

        def scores(index: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            batch = policy.obs_to_tensor({k: v[index].numpy() for k, v in tensors.items()})[0]
            q = policy.q_net(batch)
            return q, batch[ACTION_MASK_KEY].bool()

        weights = policy.q_net.parameters()
        device = policy.device  # algo.device: a GPU where there is one

    def logits(index: torch.Tensor) -> torch.Tensor:
        q, mask = scores(index)
        return q.masked_fill(~mask, -1e9)

    def predict(rows: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            index = torch.as_tensor(rows)
            return torch.cat([logits(c) for c in index.split(1024)]).cpu().numpy()

    optimizer = torch.optim.Adam(weights, lr=args.lr)
    rows = np.flatnonzero(fit)
    rng = np.random.default_rng(args.seed)
    # The targets live where the scores are computed (the network's device).
    target = target.to(device)
    weight = torch.where(target != 0, args.deviation_weight, 1.0)
    # Gains in steps, less the margin for every slot but 0, clipped; NaN: an empty slot.
    steps = np.clip(gains, -args.clip, args.clip)
    steps[:, 1:] -= args.margin_steps
    regress = torch.as_tensor(np.nan_to_num(steps, nan=0.0), dtype=torch.float32, device=device)
    valid = torch.as_tensor(~np.isnan(steps), device=device)
    for epoch in range(args.epochs):
        rng.shuffle(rows)
        total = 0.0
        for start in range(0, rows.size, args.batch):
            index = torch.as_tensor(rows[start : start + args.batch])
            on = index.to(device)
            if args.target == "label":
                loss = F.cross_entropy(logits(index), target[on], reduction="none")
                loss = (loss * weight[on]).sum() / weight[on].sum()
            else:
                error = F.smooth_l1_loss(logits(index), regress[on], reduction="none")
                loss = (error * valid[on]).sum() / valid[on].sum()
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            total += float(loss.detach()) * index.numel()
        if epoch % 5 == 4 or epoch == args.epochs - 1:
            print(f"epoch {epoch + 1}: loss {total / rows.size:.4f}")
            report("  fitted", predict(np.flatnonzero(fit)), labels[fit])
            if held.any():
                report("  held out", predict(np.flatnonzero(held)), labels[held])
    if args.out is not None:
        policy.q_net_target.load_state_dict(policy.q_net.state_dict())
        model.save(args.out)
        print(f"saved {args.out}")


if __name__ == "__main__":
    main()
