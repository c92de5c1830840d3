"""pbrdf-cl: the six-parameter polarized BRDF model (Zhu et al. 2020) on OpenCL.

Quick start::

    import pbrdf_cl
    pbrdf_cl.dop(40, [20, 45, 65], n=1.6, k=2.139, sigma=0.5, ks=0.9, kd=0.15, c=-0.3)

Angles are in degrees; phi = 180 (the default) is the in-plane geometry.  Computation runs on
the first usable OpenCL device, or on the float64 numpy reference where none is usable
(``backend="auto"``, the default; see :mod:`pbrdf_cl.device.engine`).
"""
from .analysis.designs import DesignResult, design
from .analysis.sensitivity import morris, sobol
from .analysis.sweeps import SweepResult, SweepSpec, load_spec, sweep
from .app import explore
from .compute.dense import ObjectiveResult, grid, reduce_grid
from .compute.pointwise import MODELS, aop, brdf, dop, evaluate, mueller, stokes, validate
from .device.engine import (
    Engine,
    NumpyEngine,
    get_default_engine,
    list_devices,
    probe,
    select_device,
    set_default_engine,
)
from .errors import (
    CommandError,
    DataWarning,
    DeviceUnusableError,
    DeviceWarning,
    KernelBuildError,
    OpenCLUnavailableError,
    ProgramUnusableError,
    RangeError,
    SensitivityWarning,
    SpecError,
    StoreError,
    StoreWarning,
    TooLargeError,
    TrialError,
    UnitsWarning,
)
from .fitting.images.batch import fit_batch
from .fitting.objective import objective
from .fitting.sample.inversion import compare_models, fit
from .fitting.sample.result import FitResult
from .fitting.sets.joint import fit_joint
from .fitting.sets.result import JointResult
from .io.measurements import Measurements, as_measurements, read_csv
from .model import quantities
from .store.verify import verify_store
from .version import __version__

__all__ = ["dop", "brdf", "aop", "stokes", "mueller", "evaluate", "quantities", "validate", "MODELS",
           "grid", "reduce_grid", "objective", "ObjectiveResult",
           "sweep", "load_spec", "SweepSpec", "SweepResult", "SpecError", "verify_store",
           "fit", "fit_joint", "JointResult",
           "fit_batch", "sobol", "morris", "design", "DesignResult", "compare_models", "FitResult", "explore",
           "read_csv", "as_measurements", "Measurements", "DataWarning", "Engine", "NumpyEngine", "probe",
           "OpenCLUnavailableError", "DeviceUnusableError", "DeviceWarning", "KernelBuildError", "ProgramUnusableError",
           "TrialError", "UnitsWarning", "RangeError", "TooLargeError", "StoreError", "StoreWarning", "CommandError",
           "SensitivityWarning",
           "get_default_engine", "set_default_engine", "list_devices", "select_device", "__version__"]
