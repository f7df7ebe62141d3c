"""How the service's onnxruntime calls share the cores: side by side, in order, the same numbers."""

from __future__ import annotations

import multiprocessing
import threading
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from service.core.onnx import SideBySide
from service.inference.estimator import OnnxPoseEstimator
from service.inference.model_file import load_model


def test_calls_run_on_several_threads_and_come_back_in_order() -> None:
    seen: set[str] = set()

    def call(k: int) -> int:
        seen.add(threading.current_thread().name)
        time.sleep(0.02)                                  # long enough for the second thread to take one
        return k * 10

    assert SideBySide(2).map(call, range(6)) == [0, 10, 20, 30, 40, 50]
    assert len(seen) == 2 and all(name.startswith("svrnet-onnx") for name in seen)
    seen.clear()
    assert SideBySide(1).map(call, range(3)) == [0, 10, 20]
    assert seen == {threading.current_thread().name}           # one worker: here, one after the other
    assert SideBySide(0).workers >= 1


def test_a_forked_child_starts_threads_of_its_own() -> None:
    calls = SideBySide(2)
    assert calls.map(lambda k: k, range(4)) == [0, 1, 2, 3]  # the parent's threads are started
    ctx = multiprocessing.get_context("fork")
    answers = ctx.Queue()
    child = ctx.Process(target=lambda: answers.put(calls.map(lambda k: k * 2, range(4))))
    child.start()
    child.join(20)
    if child.is_alive():
        child.kill()
        pytest.fail("the forked child's calls never ran")
    assert answers.get(timeout=5) == [0, 2, 4, 6] and child.exitcode == 0


def test_the_pose_model_side_by_side_gives_the_labels_of_one_call_after_the_other(tiny_model_path: Path) -> None:
    """Views, dropout draws and batches split over two threads: every label as one thread gives it."""
    model = load_model(tiny_model_path, threads=2)
    assert model.session.get_session_options().intra_op_num_threads == 1
    side = OnnxPoseEstimator(model, batch_slices=3)
    serial = OnnxPoseEstimator(replace(model, calls=SideBySide(1)), batch_slices=3)
    x = np.random.default_rng(0).random((7, 64, 64), np.float32) * 255
    np.testing.assert_array_equal(side.sample_labels(x, 20), serial.sample_labels(x, 20))


def test_every_core_means_the_cores_this_process_may_use(monkeypatch: pytest.MonkeyPatch) -> None:
    """A container pinned to two cores of a large host runs two calls at once, not one per host core."""
    import os

    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {3, 7}, raising=False)
    monkeypatch.setattr(os, "cpu_count", lambda: 64)
    assert SideBySide(0).workers == 2 and SideBySide(5).workers == 5
