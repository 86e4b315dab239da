"""Hydra search-path plugin: adds the config groups that splatrig plugins ship (entry point group splatrig.configs)."""

from hydra.core.config_search_path import ConfigSearchPath
from hydra.plugins.search_path_plugin import SearchPathPlugin


class SplatrigSearchPathPlugin(SearchPathPlugin):
    def manipulate_search_path(self, search_path: ConfigSearchPath) -> None:
        from framework.plugins import config_search_paths

        for path in config_search_paths():
            search_path.append(provider="splatrig-plugin", path=path)
