"""Datasets' shared machinery: the ZJU-MoCap layout (reader, writer), the synthetic studio (motions, appearance, ray
casting), boundary masks. Imports the registry (to build a body), `rig`, `splat` and core; never `lightning/`."""
