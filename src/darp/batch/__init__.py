"""Batches of surveys on one machine or a Ray cluster: ``darp process --executor ray[:ADDRESS]`` and
``darp twin generate``. One Ray Core task per survey (:mod:`darp.batch.executor`); the per-survey
work is :mod:`darp.batch.tasks` (processing) and :mod:`darp.batch.generate` (twin surveys)."""
