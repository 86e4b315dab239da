"""Body-model files shared by the body plugins and the dataset readers: `model_files` finds and reads SMPL / SMPL-X
files (imports core only, so `framework.data` may use it); `smpl_family` builds the SMPL-family BodyModel (imports
`interfaces`, `rig` and core)."""
