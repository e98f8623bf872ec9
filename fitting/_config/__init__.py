"""Model configurations in TOML: which blocks, their sizes, optional initial values, and the fit options.

- `table.py`: one TOML table (`ConfigTable`), the size limits, `StartWarning`.
- `kinds/`: what each kind a CONFIG can name declares (`BlockKind` with its typed options, `KindOptions`;
  `ModelKind`) and the built-in kinds, registered in `kinds/__init__.py`.
- `model_config.py`: `ModelConfig`, the validated configuration: the model it builds, its data-driven starts.
- `parse.py`: `parse_config` and `load_config`.
"""

from .kinds import (
    ACTUATOR as ACTUATOR,
    BLOCK_TABLES as BLOCK_TABLES,
    DEFAULT_KIND as DEFAULT_KIND,
    BlockKind as BlockKind,
    CreepOptions as CreepOptions,
    HysteresisOptions as HysteresisOptions,
    KindOptions as KindOptions,
    ModelKind as ModelKind,
    StartData as StartData,
    get_kind as get_kind,
    get_model_kind as get_model_kind,
    model_kinds as model_kinds,
    register_kind as register_kind,
    register_model_kind as register_model_kind,
    registered_kinds as registered_kinds,
    unregister_kind as unregister_kind,
)
from .model_config import MAX_STEPS as MAX_STEPS, ModelConfig as ModelConfig
from .parse import load_config as load_config, parse_config as parse_config, read_config_text as read_config_text
from .table import ConfigTable as ConfigTable, StartWarning as StartWarning
