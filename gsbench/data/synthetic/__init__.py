"""The synthetic scene generator: scenes with exact ground truth, written in the dataset layouts the
loaders read.

`builtin` (the table of built-in scenes, imports nothing heavy), `generator` (plan, render and write a
scene), `make` (a scene's folder made once, atomically), `primitives` (triangle meshes, surfaces and
albedos), `objects` and `shapes` (the objects), `textures`, `environment` (the table, room, courtyard and
sky around an object), `rigs` (camera rigs), `render` (ray casting with area sampling) and `groundtruth`
(the official GT files and initial points).
"""
