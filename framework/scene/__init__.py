"""Scene-adaptive capacity: measure what a capture needs (profile) and turn it into config choices (auto); compacting
a trained model lives in `framework.compaction`. Imports lightning/ and below; entry points use it."""
