"""Package layout that pyproject.toml cannot express: the top-level conf/ and sweeps/ folders ship inside the
`framework` package, so a non-editable install still composes every config (`pkg://framework.conf`)."""

from setuptools import find_namespace_packages, find_packages, setup

packages = (
    find_packages(include=["framework", "framework.*", "plugins", "plugins.*"])
    + find_namespace_packages(include=["hydra_plugins", "hydra_plugins.*"])
    + ["framework.conf", "framework.sweeps"]
)

setup(packages=packages, package_dir={"framework.conf": "conf", "framework.sweeps": "sweeps"})
