"""The trainer, by job: ``loop`` (steps, evaluation, ``main``), ``checkpoints`` (run directory, checkpoints,
``--resume`` / ``--init``), ``runpaths`` (the run's paths, recorded absolute and found again on ``--resume``),
``stopping`` (Ctrl-C / SIGTERM: a checkpoint and a clean stop; a resume with nothing to train), ``log``
(metrics.jsonl, TensorBoard), ``config`` (the nested ``TrainConfig``, YAML and ``--set``) and ``sections`` (its frozen
sections and the old flat keys). ``optstereo-train`` is ``optstereo.cli.train``."""
