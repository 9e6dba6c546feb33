"""The map: the Gaussians and their files, and the keyframe mapping steps.

* :mod:`.gaussian_map` — the Gaussians (parameters, seeding, pruning) and the map files.
* :mod:`.steps` — densification, the keyframe window, optimisation and refinement (a mixin of the engine).
* :mod:`.loss` — the mapping loss and the refinement's pose prior.
"""
