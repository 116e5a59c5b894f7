"""The trainer, by job: ``loop`` (steps, evaluation, ``main``), ``checkpoints`` (run directory, checkpoints,
``--resume`` / ``--init``), ``log`` (metrics.jsonl, TensorBoard), ``config`` (the nested ``TrainConfig``, YAML and
``--set``) and ``sections`` (its frozen sections and the old flat keys). ``optstereo-train`` is
``optstereo.cli.train``."""
