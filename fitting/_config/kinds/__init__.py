"""The kinds a CONFIG can name: block kinds (`[hysteresis]`, `[creep]`, `[dynamics]` → `BlockKind`, their options
a `KindOptions` dataclass) and whole-model kinds (`[observer]`, `[model]` → `ModelKind`). The built-in kinds are
registered here, in one place."""

from .base import (
    BLOCK_TABLES as BLOCK_TABLES,
    DEFAULT_KIND as DEFAULT_KIND,
    BlockKind as BlockKind,
    StartData as StartData,
    get_kind as get_kind,
    register_kind as register_kind,
    registered_kinds as registered_kinds,
    unregister_kind as unregister_kind,
)
from .creep import (
    KelvinVoigtKind as KelvinVoigtKind,
    LagKind as LagKind,
    LinearCreepKind as LinearCreepKind,
    LogarithmicKind as LogarithmicKind,
    NoCreep as NoCreep,
)
from .dynamics import TransferFunctionKind as TransferFunctionKind
from .hysteresis import (
    BoucWenKind as BoucWenKind,
    MaxwellSlipKind as MaxwellSlipKind,
    NoHysteresis as NoHysteresis,
    PlayKind as PlayKind,
    PrandtlIshlinskiiKind as PrandtlIshlinskiiKind,
    PreisachKind as PreisachKind,
)
from .models import (
    ACTUATOR as ACTUATOR,
    ModelKind as ModelKind,
    get_model_kind as get_model_kind,
    model_kinds as model_kinds,
    register_model_kind as register_model_kind,
)
from .nonlinear import BoucWenOscillatorKind as BoucWenOscillatorKind, ElectromechanicalKind as ElectromechanicalKind
from .observers import (
    CurrentIntegrationObserver as CurrentIntegrationObserver,
    DynamicImpedanceKind as DynamicImpedanceKind,
    SensorLayerKind as SensorLayerKind,
)
from .options import (
    CreepOptions as CreepOptions,
    HysteresisOptions as HysteresisOptions,
    KindOptions as KindOptions,
)

for _kind in (PrandtlIshlinskiiKind(), PlayKind(), BoucWenKind(), MaxwellSlipKind(), PreisachKind(), NoHysteresis(),
              KelvinVoigtKind(), LogarithmicKind(), LagKind(), LinearCreepKind(), NoCreep(), TransferFunctionKind()):
    register_kind(_kind)
for _model in (CurrentIntegrationObserver(), DynamicImpedanceKind(), SensorLayerKind(), BoucWenOscillatorKind(),
               ElectromechanicalKind()):
    register_model_kind(_model)
del _kind, _model
