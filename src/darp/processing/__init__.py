"""``darp process``: one processing run of a survey, above reconstruction and evaluation.

:mod:`.settings` holds the run's settings (one YAML file), :mod:`.pipeline` the job and the
reconstruction stages (poses, keyframes, fusion, mesh) with resumable stage state, :mod:`.evaluate`
the evaluation stage (held-out, cross-arm, truth metrics, figures) and :mod:`.results` the
``results.json`` of a survey and the summary of a batch.
"""
