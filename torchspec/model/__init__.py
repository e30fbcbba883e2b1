"""The measurement model: what a pixel records under each frame's light, and its derivatives.

Geometry and lights (:mod:`~torchspec.model.lights`, near lights), the maps
(:class:`~torchspec.model.brdf.SVBRDF`), the reflectance models a pixel can take
(:mod:`~torchspec.model.registry`, their parameters :mod:`~torchspec.model.params` and lobes
:mod:`~torchspec.model.lobes`), the renderer (:func:`~torchspec.model.rendering.render`) with its
quadrature, Jacobians and least-squares terms, the sensor's noise, the residual term, and cast
shadows (:mod:`~torchspec.model.height`, :mod:`~torchspec.model.visibility`). Every other stage
imports from here; nothing here imports a stage above it.
"""
