"""Datasets' shared machinery: the sequence datasets' shared keys (`options`; their names follow
`framework.dataset_keys`), the sequence dataset (views, frames, undistortion, caches), the ZJU-MoCap layout (reader,
writer) and EasyMocap's (reader, converter), the capture check (`check` is its entry point), the synthetic studio
(motions, appearance, ray casting, capture imperfections, a loose garment), boundary masks. Imports the registry (to
build a body), `interfaces`, `bodies.model_files`, `rig`, `splat` and core; never `lightning/`."""
