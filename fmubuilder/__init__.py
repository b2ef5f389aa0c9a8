"""fmubuilder: hybrid FMUs from a first-principle FMI 2.0 Model-Exchange FMU and measured data."""

__version__ = "0.1.0"
