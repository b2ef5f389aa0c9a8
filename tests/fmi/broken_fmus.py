"""Make broken variants of a good FMU, one defect each."""
import re
import zipfile
from pathlib import Path


def rewrite_fmu(source: Path, target: Path, *, xml=None, drop=()) -> Path:
    """Copy an FMU, optionally transforming modelDescription.xml and dropping entries."""
    with zipfile.ZipFile(source) as zin, zipfile.ZipFile(target, "w") as zout:
        for item in zin.infolist():
            if any(item.filename.startswith(prefix) for prefix in drop):
                continue
            data = zin.read(item.filename)
            if item.filename == "modelDescription.xml" and xml is not None:
                data = xml(data.decode()).encode()
            zout.writestr(item, data)
    return target


def set_fmi_version(version: str):
    return lambda text: text.replace('fmiVersion="2.0"', f'fmiVersion="{version}"', 1)


def co_simulation_only(text: str) -> str:
    return re.sub(r"<ModelExchange\b", "<CoSimulation", text, count=1).replace("</ModelExchange>", "</CoSimulation>")


# -- damaged archives ----------------------------------------------------------------------

def binary_name(source: Path) -> str:
    with zipfile.ZipFile(source) as zf:
        return next(n for n in zf.namelist() if n.startswith("binaries/linux64/") and n.endswith(".so"))


def flip_byte_in_entry(source: Path, target: Path, entry: str, *, compressed: bool) -> Path:
    """Copy an FMU, then damage `entry`'s data in the middle: a stored entry fails its CRC
    check, a deflated one its decompression (or CRC)."""
    with zipfile.ZipFile(source) as zin, zipfile.ZipFile(target, "w") as zout:
        for item in zin.infolist():
            method = zipfile.ZIP_DEFLATED if (item.filename != entry or compressed) else zipfile.ZIP_STORED
            zout.writestr(item.filename, zin.read(item.filename), compress_type=method)
    with zipfile.ZipFile(target) as zf:
        info = zf.getinfo(entry)
    raw = bytearray(target.read_bytes())
    name_length, extra_length = int.from_bytes(raw[info.header_offset + 26:info.header_offset + 28], "little"), \
        int.from_bytes(raw[info.header_offset + 28:info.header_offset + 30], "little")
    data_start = info.header_offset + 30 + name_length + extra_length
    middle = data_start + info.compress_size // 2
    raw[middle:middle + 8] = bytes(b ^ 0xFF for b in raw[middle:middle + 8])
    target.write_bytes(bytes(raw))
    return target


def truncate(source: Path, target: Path, fraction: float = 0.5) -> Path:
    data = source.read_bytes()
    target.write_bytes(data[: int(len(data) * fraction)])
    return target


def add_entries(source: Path, target: Path, entries: dict[str, bytes]) -> Path:
    rewrite_fmu(source, target)
    with zipfile.ZipFile(target, "a") as zf:
        for name, data in entries.items():
            zf.writestr(name, data)
    return target


def add_zip_bomb(source: Path, target: Path, megabytes: int) -> Path:
    """Copy an FMU and add resources/bomb.bin: `megabytes` of zeros, deflated about 1000:1."""
    rewrite_fmu(source, target)
    block = bytes(1 << 20)
    with zipfile.ZipFile(target, "a", compression=zipfile.ZIP_DEFLATED, compresslevel=1) as zf:
        with zf.open("resources/bomb.bin", "w", force_zip64=megabytes >= 2047) as out:
            for _ in range(megabytes):
                out.write(block)
    return target


def billion_laughs(text: str) -> str:
    """A modelDescription with exponentially nested entities in its description."""
    entities = "".join(f'<!ENTITY e{i} "{"&e%d;" % (i - 1) * 10 if i else "ha"}">' for i in range(10))
    head, sep, rest = text.partition("<fmiModelDescription")
    return f'{head}<!DOCTYPE fmiModelDescription [{entities}]>\n{sep}' + rest.replace(
        'modelName="', 'description="&e9;" modelName="', 1)


def replace_binary(source: Path, target: Path, data: bytes) -> Path:
    name = binary_name(source)
    with zipfile.ZipFile(source) as zin, zipfile.ZipFile(target, "w") as zout:
        for item in zin.infolist():
            zout.writestr(item, data if item.filename == name else zin.read(item.filename))
    return target


def declare_size(path: Path, entry: str, size: int) -> Path:
    """Rewrite the uncompressed size `entry` declares in the central directory (no zip64)."""
    raw = bytearray(path.read_bytes())
    with zipfile.ZipFile(path) as zf:
        offset = zf.start_dir
    while raw[offset:offset + 4] == b"PK\x01\x02":
        name_length, extra_length, comment_length = (int.from_bytes(raw[offset + k:offset + k + 2], "little")
                                                     for k in (28, 30, 32))
        if raw[offset + 46:offset + 46 + name_length].decode() == entry:
            raw[offset + 24:offset + 28] = size.to_bytes(4, "little")
            path.write_bytes(bytes(raw))
            return path
        offset += 46 + name_length + extra_length + comment_length
    raise KeyError(entry)
