"""Fixtures shared by the test modules."""

import pytest


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
