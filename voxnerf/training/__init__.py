"""Training, as set-up stages and a short loop with callbacks.

``train`` lives in ``voxnerf.training.run`` (and is re-exported by ``voxnerf.trainer``, the public entry point).
This package imports nothing on its own, so ``voxnerf.training.records`` (the report, stage, evaluation and
progress-event models) can be imported without torch.

Modules: ``records`` (what travels out), ``budget`` (time budget), ``stages`` (set-up stages), ``pixels``
(training pixels and batches), ``step`` (loss, step, divergence guard), ``loop`` (the loop), ``callbacks``
(its periodic duties), ``evals`` (progress and final evaluations), ``checkpoint`` (checkpoint and report
files), ``run`` (``train()``).
"""
