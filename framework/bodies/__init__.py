"""Body-model files shared by the body plugins and the dataset readers: SMPL / SMPL-X file lookup and loading.

May import framework.interfaces, framework.errors, framework.registry and the math modules (geometry, kinematics)."""
