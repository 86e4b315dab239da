"""The ZJU-MoCap / Neural Body layout: `layout` (naming, file formats), `writer`, `reader`, `protocols` (published
view/frame splits) and `dataset` (the training dataset). Imports `framework.data.sequence_dataset` and core."""
