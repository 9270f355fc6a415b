"""The fitted field, and the field rendered into per-frame masks.

``field.FittedField`` is what expand fits (geometry + semantic head + classes, normalisation
and recipe); ``renderer.FieldRenderer`` renders it (with its head or any other) and caches the
surface; ``surface`` extracts the SDF's zero level set and casts camera rays onto it;
``config.RenderConfig`` holds the recipe's ``render`` section. Import from the modules: this
package's ``__init__`` imports none of them, because ``recipe`` imports ``render.config`` and
the field imports ``recipe``.
"""
