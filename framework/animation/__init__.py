"""Driving a trained avatar outside training: where poses come from (dataset splits, motion files), one posed frame
as a batch or a render, camera paths, and the exports. Shared by the render, view and export entry points.

May import lightning/ (a loaded SplatModule is the input), data/, formats/ and the core; never the entry points.
"""
