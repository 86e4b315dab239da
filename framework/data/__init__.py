"""Datasets' shared machinery: the ZJU-MoCap layout (reader, writer), the synthetic studio (motions, appearance, ray
casting, capture imperfections, a loose garment), boundary masks. Imports the registry (to build a body), `rig`,
`splat` and core; never `lightning/`."""
