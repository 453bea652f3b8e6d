"""Scenes: cameras, images, masks, initial points and a handle to the ground truth.

The loaders of the real layouts sit here (`dtu`: the IDR and 2DGS COLMAP layouts, `tnt`: Tanks and
Temples, `colmap`, `images`, `filecheck`, `meta`, `resolution`, `visual_hull`), the scene types in
`camera`, and the synthetic scene generator in its own subpackage, `synthetic`.
`loader.load_scene(path_or_name)` detects a folder's layout and reads it, or reads a built-in scene
(``synthetic/<name>``) from the cache, where `synthetic.make.ensure_scene` made it first.
"""
