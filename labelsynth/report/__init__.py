"""The consistency report of an expand run: which input masks disagree, where, and by how much.

``build.build_report`` receives what it needs from the caller (the field's renderer, the masks
it learnt from, a callable that gives the leave-one-out heads), so this package imports no
orchestration; ``pipeline.expand`` and ``pipeline.rebuild_report`` call it. ``config`` holds
the recipe's ``report`` section. Import from the modules: this ``__init__`` imports none of
them (``recipe`` imports ``report.config``, and ``build`` draws its plots with matplotlib).
"""
