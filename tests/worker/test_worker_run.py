"""How a worker process starts (:mod:`worker.run`): the OpenMP wait policy each kind of worker loads torch with."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from worker.run import openmp_wait_policy, set_openmp_wait_policy


@pytest.mark.parametrize(
    ("queues", "expected"),
    [(["train"], None), (["train", "render", "outputs"], None), (["render"], "PASSIVE"), (["outputs"], "PASSIVE"),
     (["render", "outputs"], "PASSIVE")],
)
def test_a_training_worker_keeps_the_cli_s_policy_and_render_workers_sleep_at_once(queues, expected):
    assert openmp_wait_policy(queues) == expected


def test_the_environment_s_policy_wins():
    env = {"OMP_WAIT_POLICY": "ACTIVE"}
    assert set_openmp_wait_policy(["render"], env) == "ACTIVE" and env == {"OMP_WAIT_POLICY": "ACTIVE"}
    env = {}
    assert set_openmp_wait_policy(["render"], env) == "PASSIVE" and env == {"OMP_WAIT_POLICY": "PASSIVE"}
    env = {}
    assert set_openmp_wait_policy(["train"], env) is None and env == {}


def test_starting_a_worker_sets_the_policy_before_torch_loads():
    """``worker.run`` loads no torch (OpenMP reads the policy once, when torch loads it), and the policy it sets
    is the one torch's process then has; a worker that trains sets none."""
    code = ("import sys, os; import worker.run as w; assert 'torch' not in sys.modules; "
            "w.set_openmp_wait_policy(sys.argv[1].split(',')); import worker.tasks; "
            "assert 'torch' in sys.modules; print(os.environ.get('OMP_WAIT_POLICY'))")
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    cases = (("render", "PASSIVE"), ("outputs", "PASSIVE"), ("train", "None"), ("train,render", "None"))
    for queues, expected in cases:
        out = subprocess.run([sys.executable, "-c", code, queues], env=env, capture_output=True, text=True, check=True)
        assert out.stdout.strip() == expected, queues


def test_torch_loaded_too_early_is_said(caplog, monkeypatch):
    monkeypatch.setitem(sys.modules, "torch", sys.modules.get("torch") or object())
    with caplog.at_level("WARNING", logger="worker.run"):
        set_openmp_wait_policy(["render"], {})
    assert "torch loaded before the worker set OMP_WAIT_POLICY=PASSIVE" in caplog.text
