"""``harness bench`` runs and reports its figures (no timing is asserted: they vary by machine)."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import pytest

from harness.bench import (
    GOALS_TRANSITIONS_PER_STEP,
    TRAIN_NETS,
    bench_sharing,
    bench_train,
    format_bench,
    machine_info,
)
from harness.cli import main
from harness.config.loading import load_config

ROOT = Path(__file__).resolve().parents[1]


def test_bench_env_json_has_the_documented_keys(capsys):
    assert main(["bench", "env", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    for key in (
        "env_bare_agent_steps_per_s",
        "env_bare_teammap_agent_steps_per_s",
        "env_teammap_over_thesis",
        "env_bare_teammap_ego_agent_steps_per_s",
        "env_bare_teammap_frontier_agent_steps_per_s",
        "env_bare_teammap_claims_agent_steps_per_s",
        "env_bare_teammap_pocket_agent_steps_per_s",
        "env_bare_goals_agent_steps_per_s",
        "env_bare_goals_prior_agent_steps_per_s",
        "env_goals_prior_over_goals",
        "env_bare_goals_predicted_agent_steps_per_s",
        "env_vec_agent_steps_per_s",
        "env_vec_over_bare",
    ):
        assert out[key] > 0
    assert set(out["env_vec_by_copies"]) == {"1", "4", "16", "64"}
    assert set(out["env_vec_supersuit_by_copies"]) == set(out["env_vec_by_copies"])
    assert all(v > 0 for v in out["env_vec_core_over_supersuit"].values())
    assert out["torch_threads"] >= 1 and out["python"]


def test_bench_report_shows_every_section_with_targets():
    figures = {
        **machine_info(),
        "env_bare_agent_steps_per_s": 120_000.0,
        "env_bare_teammap_agent_steps_per_s": 36_000.0,
        "env_bare_teammap_ego_agent_steps_per_s": 24_000.0,
        "env_bare_teammap_frontier_agent_steps_per_s": 6_000.0,
        "env_bare_teammap_claims_agent_steps_per_s": 4_800.0,
        "env_bare_teammap_pocket_agent_steps_per_s": 3_600.0,
        "env_bare_goals_agent_steps_per_s": 3_000.0,
        "env_bare_goals_prior_agent_steps_per_s": 150.0,
        "env_bare_goals_predicted_agent_steps_per_s": 120.0,
        "env_vec_by_copies": {1: 40_000.0, 4: 50_000.0, 16: 520_000.0},
        "env_vec_supersuit_by_copies": {1: 40_000.0, 4: 50_000.0, 16: 52_000.0},
        "env_vec_agent_steps_per_s": 50_000.0,
        "env_vec_over_bare": 50_000 / 120_000,
        "env_vec_8_copies_by_processes": {0: 51_000.0, 2: 33_000.0},
        "train_grad_steps_per_s": 200.0,
        "train_grad_steps_per_s_plain_dqn": 240.0,
        "train_grad_steps_ratio": 200 / 240,
        "train_transitions_per_s": 4000.0,
        "train_transitions_per_s_plain_dqn": 5000.0,
        "train_transitions_ratio": 0.8,
        "train_grad_steps_by_device": {
            "cpu": {
                "mlp_3x512": {"doubledqn_per": 200.0, "dqn": 240.0, "ratio": 200 / 240},
                "teammap_cnn": {"doubledqn_per": 36.0, "dqn": 45.0, "ratio": 0.8},
            },
            "cuda": {
                "teammap_cnn": {
                    "doubledqn_per": 1_500.0,
                    "dqn": 1_250.0,
                    "doubledqn_per_no_graph": 300.0,
                    "ratio": 1.2,
                    "graph_gain": 5.0,
                }
            },
        },
        "train_grad_steps_per_s_by_setting": {
            "2x64/batch32/threads1": 500.0,
            "2x64/batch32/threads2": 450.0,
        },
        "eval_episodes_per_s": 8.0,
        "eval_100_episodes_s": 12.5,
        "eval_frontier_episodes_per_s": 11.0,
        "eval_frontier_pocket_episodes_per_s": 7.5,
        "eval_frontier_pocket_over_frontier": 7.5 / 11.0,
        "eval_frontier_hungarian_episodes_per_s": 5.5,
        "eval_frontier_hungarian_over_frontier": 0.5,
        "eval_rollout_threads": 2,
        "eval_rollout_episodes_per_s": 0.09,
        "eval_rollout_1_thread_episodes_per_s": 0.06,
        "eval_rollout_over_1_thread": 1.5,
        "train_peak_memory_mib": 370.0,
    }
    text = format_bench(figures)
    for expected in (
        "120,000",
        "36,000",
        "24,000",
        "0.30 x thesis",
        "0.42",
        "target >= 0.85",
        "0.83",
        "100 episodes in 12 s",
        "370 MiB",
    ):
        assert expected in text, expected
    assert "2x64" in text and "450" in text
    (line,) = [line for line in text.splitlines() if "cpu" in line and "teammap_cnn" in line]
    assert line.split()[2:] == ["36", "45", "0.80", "-"]  # no CUDA graph on a CPU
    (line,) = [line for line in text.splitlines() if "cuda" in line and "teammap_cnn" in line]
    assert line.split()[2:] == ["1,500", "1,250", "1.20", "300"]
    (line,) = [line for line in text.splitlines() if "VecEnv, 16 copies" in line]
    assert "520,000" in line and "SuperSuit    52,000" in line and "10.0 x SuperSuit" in line
    (line,) = [line for line in text.splitlines() if "teammap + frontier field" in line]
    assert "6,000" in line and "0.05 x thesis" in line
    (line,) = [line for line in text.splitlines() if "frontier claims" in line]
    assert "4,800" in line and "0.04 x thesis" in line
    (line,) = [line for line in text.splitlines() if "pocket tie-break" in line]
    assert "3,600" in line and "0.03 x thesis" in line
    # The map prior's row over the goal action's, the predicted views' over the prior's.
    (line,) = [line for line in text.splitlines() if "map prior (env.prior)" in line]
    assert "150" in line and "0.05 x goal action" in line
    (line,) = [line for line in text.splitlines() if "predicted views" in line]
    assert "120" in line and "0.80 x map prior" in line
    (line,) = [line for line in text.splitlines() if "frontier_pocket episodes/s" in line]
    assert "7.50" in line and "0.68 x frontier" in line
    (line,) = [line for line in text.splitlines() if "frontier_hungarian episodes/s" in line]
    assert "5.50" in line and "0.50 x frontier" in line
    (line,) = [line for line in text.splitlines() if "rollout episodes/s" in line]
    assert "0.090" in line and "2 threads; 1.50 x 1 thread (0.060)" in line


def test_bench_eval_has_a_key_per_planner(monkeypatch: pytest.MonkeyPatch) -> None:
    from envs.coverage.frontier import PLANNERS
    from harness import bench, processes
    from harness.bench import bench_eval

    # The rollout chooser's rows on a small map, on one thread and on two.
    small = bench.ROLLOUT_ENV.model_copy(update={"height": 16, "width": 16, "max_steps": 150})
    monkeypatch.setattr(bench, "ROLLOUT_ENV", small)
    monkeypatch.setattr(processes, "available_cores", lambda: 2)
    out = bench_eval(episodes=1)
    for entry in PLANNERS.values():
        assert out[f"eval_{entry.baseline}_episodes_per_s"] > 0
    assert set(k for k in out if k.endswith("_over_frontier")) == {
        f"eval_{e.baseline}_over_frontier" for e in PLANNERS.values() if e.baseline != "frontier"
    }
    # The planner's step through the team map and through the goal action's candidates.
    assert out["eval_teammap_frontier_step_episodes_per_s"] > 0
    assert out["eval_goals_frontier_step_episodes_per_s"] > 0
    # Every row per CPU second too (what a busy machine moves less).
    rows = {"mlp", "random", *(e.baseline for e in PLANNERS.values())}
    rows |= {"teammap_frontier_step", "goals_frontier_step", "rollout_threads1", "rollout_threads2"}
    assert set(out["eval_episodes_per_cpu_s"]) == rows
    assert out["eval_rollout_threads"] == 2
    assert out["eval_rollout_over_1_thread"] == pytest.approx(
        out["eval_rollout_episodes_per_s"] / out["eval_rollout_1_thread_episodes_per_s"]
    )
    assert all(rate > 0 for rate in out["eval_episodes_per_cpu_s"].values())


def test_bench_teacher_times_the_labels_on_one_thread_and_on_every_core(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from harness import bench, processes

    small = bench.ROLLOUT_ENV.model_copy(update={"height": 16, "width": 16, "max_steps": 150})
    monkeypatch.setattr(bench, "ROLLOUT_ENV", small)
    monkeypatch.setattr(processes, "available_cores", lambda: 2)
    out = bench.bench_teacher(rounds=1, copies=3, warm_steps=5)
    assert out["train_teacher_threads"] == 2
    assert out["train_teacher_labels_per_s"] > 0 and out["train_teacher_1_thread_labels_per_s"] > 0
    assert out["train_teacher_over_1_thread"] == pytest.approx(
        out["train_teacher_labels_per_s"] / out["train_teacher_1_thread_labels_per_s"]
    )
    text = bench.format_bench({**machine_info(), **out})
    assert "true-map teacher's labels/s (4 agents, 3 copies)" in text


def test_bench_sharing_reports_gradient_steps_per_mode():
    out = bench_sharing(net=[8], batch=4, grad_steps=2, fill=64)
    rates = out["train_grad_steps_per_s_by_sharing"]
    assert list(rates) == ["shared", "shared_id", "per_agent"]
    assert all(rate > 0 for rate in rates.values())
    text = format_bench({**machine_info(), **out})
    assert "by algo.sharing" in text and "x shared" in text


def test_bench_train_times_both_learners_per_net_on_the_cpu_alone_without_cuda(monkeypatch):
    import torch

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    # The real nets and envs, with tiny buffers and calls.
    nets = {n: dataclasses.replace(net, fill=64, buffer_size=512) for n, net in TRAIN_NETS.items()}
    out = bench_train(rounds=1, grad_steps=4, transitions=32, nets=nets)
    by_device = out["train_grad_steps_by_device"]
    assert list(by_device) == ["cpu"]
    assert list(by_device["cpu"]) == ["mlp_3x512", "teammap_cnn", "goal_slots"]
    for row in by_device["cpu"].values():
        assert list(row) == ["doubledqn_per", "dqn", "ratio"]
        assert all(math.isfinite(v) and v > 0 for v in row.values())
        assert row["ratio"] == pytest.approx(row["doubledqn_per"] / row["dqn"])
    # The flat keys keep their meaning: the MLP on the CPU.
    mlp = by_device["cpu"]["mlp_3x512"]
    assert out["train_grad_steps_per_s"] == mlp["doubledqn_per"]
    assert out["train_grad_steps_per_s_plain_dqn"] == mlp["dqn"]
    assert out["train_grad_steps_ratio"] == mlp["ratio"]
    for key in ("train_transitions_per_s", "train_transitions_per_s_plain_dqn"):
        assert math.isfinite(out[key]) and out[key] > 0
    text = format_bench({**machine_info(), **out})
    assert "by device and network" in text and "cuda" not in text
    floor = GOALS_TRANSITIONS_PER_STEP * by_device["cpu"]["goal_slots"]["doubledqn_per"]
    assert f"goals_2agents on the cpu: at most {floor:,.0f} transitions/s" in text


def test_the_goal_configs_gradient_step_comes_every_16_transitions():
    # The floor the report prints for goals_2agents: train_freq vector steps of copies x agents
    # slots, so many gradient steps each (the phase's epochs).
    config = load_config(ROOT / "configs" / "goals_2agents.yaml", [])
    phase = config.phases[0]
    ((_, epochs),) = phase.epochs
    slots = config.vec.copies * config.env.n_agents
    assert phase.train_freq * slots / epochs == GOALS_TRANSITIONS_PER_STEP


def test_bench_help_names_every_section_once(capsys):
    from harness.bench import SECTION_HELP, SECTIONS

    assert SECTION_HELP.keys() == SECTIONS.keys()
    assert main(["bench", "--help"]) == 0
    out = capsys.readouterr().out
    for name, line in SECTION_HELP.items():
        assert f"  {name:9} {line}\n" in out
    assert "{env,train,sharing,eval,memory,all}" in out
