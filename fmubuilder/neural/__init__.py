"""NeuralFMU: an FMU as a differentiable layer inside a small ANN topology, simulated with FMI event
handling and trained on measured data (PyTorch). Its names load on first use (_lazy.py).

    from fmubuilder.neural import train_neural_fmu, load_neural_fmu
    result = train_neural_fmu("vldm.fmu", "train.csv", targets=["der(speed)"], inputs=["speed", "der(speed)"])
"""
from __future__ import annotations

from .._lazy import lazy_exports

_EXPORTS = {
    "NeuralFMU": "model", "TopologyConfig": "topology", "Topology": "topology",
    "simulate": "solve", "ElementStart": "solve", "Trajectory": "solve",
    "train_neural_fmu": "train", "TrainSettings": "settings", "TrainingResult": "train", "evaluate": "train",
    "save_neural_fmu": "io", "load_neural_fmu": "io", "read_neural_fmu": "io",
    "NeuralFmuSystem": "system", "simulate_hybrid": "system",
}

__all__ = sorted(_EXPORTS)
__getattr__ = lazy_exports(__name__, _EXPORTS)
