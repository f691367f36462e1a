"""Seeing what the localizer sees: overlays, plots, the replay report, the live view.

A layer above ``sim`` and below the orchestration at runtime/'s top (which calls it):
:mod:`.overlay` (pure drawing), :mod:`.tap` (the latest frame and estimate, by
reference), :mod:`.plots` (matplotlib, Agg, imported lazily), :mod:`.report` (the
self-contained HTML replay report), :mod:`.web` (the live web view).
"""
