"""Fixtures shared by the test modules."""

import importlib.util
from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def results_script():
    """Load a ``docs/results/<name>.py`` analysis script (not a package module) by name."""

    def load(name: str):
        path = Path(__file__).resolve().parents[1] / "docs" / "results" / f"{name}.py"
        spec = importlib.util.spec_from_file_location(name, path)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module

    return load


@pytest.fixture
def step_counter():
    """A factory of Trainer callbacks that record the step a run began at and count its optimizer
    steps (to see that a resumed run takes only the steps not yet taken)."""
    from transformers import TrainerCallback

    class StepCounter(TrainerCallback):
        def __init__(self):
            self.begin, self.steps = None, 0

        def on_train_begin(self, args, state, control, **kw):
            self.begin = state.global_step

        def on_step_end(self, args, state, control, **kw):
            self.steps += 1

    return StepCounter
