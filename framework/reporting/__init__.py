"""Reports over many runs' results records (results.json): collecting runs, seed statistics, and one module per
report kind (table4: the paper's ablation table). May import framework.evaluation and framework's core; not
lightning/ or entry points."""
