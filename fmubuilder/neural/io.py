"""Save and load a trained NeuralFMU: one file holding the topology config (JSON-able), the trained
tensors, the start values and the FMU it wraps (path, GUID and SHA-256, checked on load)."""
from __future__ import annotations

import io
import warnings
from pathlib import Path

import torch

from ..errors import FmuBuilderError
from ..files import file_sha256, refuse_existing, write_atomically
from ..fmi import read_model_info
from .model import NeuralFMU
from .topology import TopologyConfig

FORMAT = "fmubuilder-neuralfmu/1"


def save_neural_fmu(model: NeuralFMU, path: str | Path, *, metadata: dict | None = None, force: bool = True) -> Path:
    """Write `model` to `path` (atomically); `metadata` (JSON-able) is stored alongside."""
    path = refuse_existing(path, force)
    payload = {
        "format": FORMAT,
        "config": model.config.to_dict(),
        "state_dict": {k: v.detach().clone() for k, v in model.topology.state_dict().items()},
        "start_values": dict(model.start_values),
        "fmu": {"path": str(model.fmu_path.resolve()), "guid": model.guid,
                "model_name": model.info.model_name, "sha256": file_sha256(model.fmu_path)},
        "metadata": metadata or {},
    }
    buffer = io.BytesIO()
    torch.save(payload, buffer)
    return write_atomically(path, buffer.getvalue())


def read_neural_fmu(path: str | Path) -> dict:
    """The saved payload (config, tensors, FMU reference) without loading the FMU."""
    path = Path(path)
    if not path.is_file():
        raise FmuBuilderError(f"{path}: no such file; give the path of a trained NeuralFMU (`fmubuilder train -o`)")
    try:
        with warnings.catch_warnings():  # torch warns about foreign pickles before failing on them
            warnings.simplefilter("ignore")
            payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many kinds for a file that is not its format
        raise FmuBuilderError(f"{path} is not a trained NeuralFMU file ({type(exc).__name__}); "
                              "create one with `fmubuilder train`") from None
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise FmuBuilderError(f"{path} is not a {FORMAT} file; create it with `fmubuilder train`")
    return payload


def load_neural_fmu(path: str | Path, fmu: str | Path | None = None) -> NeuralFMU:
    """Load a trained NeuralFMU; `fmu` overrides the stored FMU path (it must have the same GUID)."""
    payload = read_neural_fmu(path)
    stored = payload["fmu"]
    fmu_path = Path(fmu) if fmu is not None else Path(stored["path"])
    if not fmu_path.is_file():
        raise FmuBuilderError(f"{path} wraps {stored['path']}, which does not exist; pass the FMU's new location")
    info = read_model_info(fmu_path)
    if info.guid != stored["guid"]:
        raise FmuBuilderError(f"{fmu_path} has GUID {info.guid}, but {path} was trained on {stored['model_name']} "
                              f"with GUID {stored['guid']}; give the FMU it was trained on")
    model = NeuralFMU(fmu_path, TopologyConfig.from_dict(payload["config"]), payload["start_values"])
    try:
        model.topology.load_state_dict(payload["state_dict"])
    except RuntimeError as exc:
        model.close()
        raise FmuBuilderError(f"{path}: the stored tensors do not fit the stored topology ({exc})") from None
    model.metadata = payload.get("metadata", {})
    return model
