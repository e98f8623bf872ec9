"""piezojax: differentiable models of piezoelectric actuators and their self-sensing electronics."""

from ._actuator import (
    Actuator as Actuator,
    ActuatorOutput as ActuatorOutput,
)
from ._actuator_inverse import ActuatorInverse as ActuatorInverse
from ._benches.bafumba import (
    BafumbaBench as BafumbaBench,
    unimorph_dynamics as unimorph_dynamics,
)
from ._benches.chen import ChenBench as ChenBench, ChenStagePlant as ChenStagePlant
from ._benches.common import (
    AbstractBench as AbstractBench,
    AbstractSelfSensingBench as AbstractSelfSensingBench,
    Record as Record,
    step_command as step_command,
)
from ._benches.ivan import (
    IvanBench as IvanBench,
    periodic_steps as periodic_steps,
)
from ._benches.quant import QuantBench as QuantBench, charge_preisach as charge_preisach
from ._checks import PiezojaxError as PiezojaxError, PiezojaxValueError as PiezojaxValueError
from ._circuits.base import AbstractCircuit as AbstractCircuit
from ._circuits.charge_integrator import ChargeIntegratorCircuit as ChargeIntegratorCircuit
from ._circuits.smart_stack import SmartStackCircuit as SmartStackCircuit
from ._circuits.transimpedance import TransimpedanceCircuit as TransimpedanceCircuit
from ._config import (
    enable_compilation_cache as enable_compilation_cache,
    enable_fast_cpu_scans as enable_fast_cpu_scans,
    release_freed_memory as release_freed_memory,
    retain_freed_memory as retain_freed_memory,
    set_parallel_scans as set_parallel_scans,
)
from ._control.adaptive_inverse import AdaptiveInverseController as AdaptiveInverseController
from ._control.base import AbstractController as AbstractController, AbstractPlant as AbstractPlant
from ._control.feedforward import (
    FeedforwardFeedback as FeedforwardFeedback,
    InverseFeedforward as InverseFeedforward,
)
from ._control.loop import (
    LoopRecord as LoopRecord,
    closed_loop as closed_loop,
    tracking_error_percent as tracking_error_percent,
)
from ._control.narx import NarxNetwork as NarxNetwork, train_narx_online as train_narx_online
from ._control.pid import PID as PID
from ._creep.base import AbstractCreep as AbstractCreep, AbstractFusedCreep as AbstractFusedCreep
from ._creep.kelvin_voigt import KelvinVoigtCreep as KelvinVoigtCreep
from ._creep.lag import LagCreep as LagCreep
from ._creep.linear import LinearCreep as LinearCreep
from ._creep.logarithmic import LogarithmicCreep as LogarithmicCreep
from ._custom_types import AbstractCell as AbstractCell
from ._hysteresis.base import (
    AbstractFusedHysteresis as AbstractFusedHysteresis,
    AbstractHysteresis as AbstractHysteresis,
    AbstractHysteresisCell as AbstractHysteresisCell,
    HysteresisInverse as HysteresisInverse,
)
from ._hysteresis.bouc_wen import BoucWen as BoucWen
from ._hysteresis.initialise import (
    pi_cold_start as pi_cold_start,
    pi_weights_least_squares as pi_weights_least_squares,
)
from ._hysteresis.maxwell_slip import MaxwellSlip as MaxwellSlip
from ._hysteresis.play import (
    PlayOperator as PlayOperator,
    StopOperator as StopOperator,
)
from ._hysteresis.polynomial import OutputPolynomial as OutputPolynomial
from ._hysteresis.prandtl_ishlinskii import PrandtlIshlinskii as PrandtlIshlinskii
from ._hysteresis.preisach import (
    GaussianPreisach as GaussianPreisach,
    Preisach as Preisach,
)
from ._hysteresis.scaled import ScaledHysteresis as ScaledHysteresis
from ._linear.base import AbstractLinearSystem as AbstractLinearSystem, StateSpace as StateSpace
from ._linear.butterworth import butterworth as butterworth
from ._linear.delay import Delay as Delay
from ._linear.discretise import (
    DiscreteStateSpace as DiscreteStateSpace,
    discretise_state_space as discretise_state_space,
    time_step as time_step,
)
from ._linear.stable import StableTransferFunction as StableTransferFunction
from ._linear.transfer_function import TransferFunction as TransferFunction
from ._nonlinear._input import (
    SampledInput as SampledInput,
    simulate_ode as simulate_ode,
)
from ._nonlinear.bouc_wen_oscillator import BoucWenOscillator as BoucWenOscillator
from ._nonlinear.electromechanical import (
    ElectromechanicalActuator as ElectromechanicalActuator,
    ElectromechanicalInverse as ElectromechanicalInverse,
)
from ._observers.base import (
    AbstractObserver as AbstractObserver,
    Estimate as Estimate,
)
from ._observers.current_integration import ForceDisplacementObserver as ForceDisplacementObserver
from ._observers.dynamic_impedance import DynamicImpedanceObserver as DynamicImpedanceObserver
from ._observers.sensor_layer import SensorLayerObserver as SensorLayerObserver
from ._parametrisation import (
    AbstractReparam as AbstractReparam,
    Bounded as Bounded,
    Fractions as Fractions,
    OrderedPositive as OrderedPositive,
    Positive as Positive,
    constrain as constrain,
    inv_softplus as inv_softplus,
    setting as setting,
    setting_key_paths as setting_key_paths,
    softplus as softplus,
    unwrap as unwrap,
)

# the public names (the API reference documents each; tests/test_docs.py checks both lists)
__all__ = [
    "AbstractBench", "AbstractCell", "AbstractCircuit", "AbstractController", "AbstractCreep",
    "AbstractFusedCreep", "AbstractFusedHysteresis", "AbstractHysteresis", "AbstractHysteresisCell",
    "AbstractLinearSystem", "AbstractObserver", "AbstractPlant", "AbstractReparam", "AbstractSelfSensingBench",
    "Actuator", "ActuatorInverse", "ActuatorOutput", "AdaptiveInverseController", "BafumbaBench", "BoucWen",
    "BoucWenOscillator", "Bounded", "ChargeIntegratorCircuit", "ChenBench", "ChenStagePlant", "Delay",
    "DiscreteStateSpace", "DynamicImpedanceObserver", "ElectromechanicalActuator", "ElectromechanicalInverse",
    "Estimate", "FeedforwardFeedback", "ForceDisplacementObserver", "Fractions", "GaussianPreisach",
    "HysteresisInverse", "InverseFeedforward", "IvanBench", "KelvinVoigtCreep", "LagCreep", "LinearCreep",
    "LogarithmicCreep", "LoopRecord", "MaxwellSlip", "NarxNetwork", "OrderedPositive", "OutputPolynomial",
    "PID", "PiezojaxError", "PiezojaxValueError", "PlayOperator", "Positive", "PrandtlIshlinskii", "Preisach",
    "QuantBench", "Record", "SampledInput", "ScaledHysteresis", "SensorLayerObserver", "SmartStackCircuit",
    "StableTransferFunction", "StateSpace", "StopOperator", "TransferFunction", "TransimpedanceCircuit",
    "butterworth", "charge_preisach", "closed_loop", "constrain", "discretise_state_space",
    "enable_compilation_cache", "enable_fast_cpu_scans", "inv_softplus", "periodic_steps", "pi_cold_start",
    "pi_weights_least_squares", "release_freed_memory", "retain_freed_memory", "set_parallel_scans", "setting",
    "setting_key_paths", "simulate_ode", "softplus", "step_command", "time_step", "tracking_error_percent",
    "train_narx_online", "unimorph_dynamics", "unwrap",
]

__version__ = "0.3.0"
