"""Synthetic training data (issue #3).

- `shapes`: random procedural shapes, one watertight outer surface, unit-sphere normalized.
- `envmaps`: the environment map pool -- natural HDR maps with augmentation, and procedural maps.
- `rigs`: the paper's camera rigs (5, 10 and 20 views).

Submodules are not imported here, so importing one does not pull in the others' dependencies.
"""
