"""``darp process``: one processing run of a survey, above reconstruction and evaluation.

:mod:`.settings` holds the run's settings (one YAML file); :mod:`.job` the survey job (:func:`~.job.open_job`: a survey
folder with its calibration, settings and output folder, and what the stages share); :mod:`.stages` the stages (poses,
keyframes, fusion, mesh, evaluation), each declaring its outputs; :mod:`.runner` runs stages in order with resume
fingerprints (``stages.json``), ``UNFINISHED.txt`` and staged ``.partial`` outputs; :mod:`.evaluate` computes the
evaluation stage's numbers (held-out, cross-arm, truth metrics, figures); :mod:`.diagnostics` says in one line why a
survey failed or looks implausible; :mod:`.results` writes and reads ``results.json`` of a survey and the summary of a
batch; :mod:`.batch` processes a survey folder (or a ``darp import`` folder, :mod:`.imported`, its measured surface in
:mod:`.imported_surface`) and a batch that goes on past failures; :mod:`.report` writes ``darp report``'s tables and
figures.
"""
