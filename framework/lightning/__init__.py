"""Training with Lightning: the LightningModule, the DataModule and the callbacks (progress, stage switch, image
grids). Imports `model`, `data`, interfaces and core; only entry points import it."""
