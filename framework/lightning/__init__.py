"""Training with Lightning: the LightningModule, the DataModule and the callbacks (progress, stage switch, image
grids), the divergence guard, atomic checkpoint I/O and trained models loaded back. Imports `model`, `data`,
`evaluation`, interfaces and core; entry points, `scene`, `viewer` and `compaction` import it."""
