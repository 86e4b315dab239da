"""Package layout that pyproject.toml cannot express: the top-level conf/ and sweeps/ folders ship inside the
`framework` package, so a non-editable install still composes every config (`pkg://framework.conf`)."""

from setuptools import find_namespace_packages, find_packages, setup


def shipped_as(folder: str, package: str) -> list[str]:
    """`package` and one package per sub-folder of `folder` (the config groups), so setuptools installs each
    folder's YAML files as package data of a declared package."""
    groups = find_namespace_packages(where=folder, exclude=["__pycache__", "*.__pycache__"])
    return [package] + [f"{package}.{group}" for group in groups]


packages = (
    find_packages(include=["framework", "framework.*", "plugins", "plugins.*"])
    + find_namespace_packages(include=["hydra_plugins", "hydra_plugins.*"])
    + shipped_as("conf", "framework.conf")
    + shipped_as("sweeps", "framework.sweeps")
)

setup(packages=packages, package_dir={"framework.conf": "conf", "framework.sweeps": "sweeps"})
