"""Configuration: one system for every command, defaults < project file < command-line flags.

- `options`: each command's options declared once (parameter, file key, flag, help): CALIBRATE, RECONSTRUCT, OPTICS.
- `files`: reading TOML/JSON files and the project folder; `merge`: the one merge rule over layers.
- `calibration` (the calibration `Config`, its TOML and the thesis's .ini), `reconstruction`, `optics`: each
  command's layers (file, flags) and the type they build.
- `messages`: library errors name parameters in backticks; the CLI line names the command's flags.
Modules here import only the standard library at import time (`dstereo --help` reads the tables).
"""

from dstereo.config.calibration import Config, build_config, find_project_config, load_config, validate
from dstereo.config.merge import merge, merge_layers
from dstereo.config.messages import with_flags
from dstereo.config.options import CALIBRATE, OPTICS, RECONSTRUCT, Option, OptionTable, flags_of
from dstereo.config.steps import Step

__all__ = ["CALIBRATE", "OPTICS", "RECONSTRUCT", "Config", "Option", "OptionTable", "Step", "build_config",
           "find_project_config", "flags_of", "load_config", "merge", "merge_layers", "validate", "with_flags"]
