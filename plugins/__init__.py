"""Built-in components. Each subpackage registers one kind through the splatrig.plugins entry points."""
