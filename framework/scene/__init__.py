"""Scene-adaptive capacity: measure what a capture needs (profile), turn it into config choices (auto), and compact a
trained model (pruning). Imports lightning/, model/, data/, interfaces/, rig/, splat/ and core; entry points use it."""
