"""Training with Lightning: the LightningModule, the DataModule and the callbacks (progress, stage switch, image
grids), the divergence guard and atomic checkpoint I/O. Imports `model`, `data`, interfaces and core; only entry
points import it."""
