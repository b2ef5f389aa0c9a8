"""FMU access: open an FMI 2.0 Model-Exchange FMU, load its binary, call its C API."""
from .archive import FmuArchive, read_model_info
from .instance import EventInfo, Fmu, FmuCallError, FmuInstance, convert_value
from .model import Capabilities, DefaultExperiment, ModelInfo, Variable

__all__ = ["Fmu", "FmuInstance", "FmuArchive", "FmuCallError", "EventInfo", "ModelInfo", "Variable",
           "Capabilities", "DefaultExperiment", "read_model_info", "convert_value"]
