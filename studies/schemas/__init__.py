"""JSON Schemas (draft 2020-12) of the files the commands write, shipped with the package.

====================  ==================================  ====================================================
name                  file                                validates
====================  ==================================  ====================================================
``study``             ``study.schema.json``               ``results.json`` of a study (``cfdesign.study/1``)
``schedule``          ``schedule.schema.json``            ``schedule.json`` of a design (``cfdesign.schedule/1``)
``feasibility``       ``feasibility.schema.json``         one row of ``feasibility.csv`` as
                                                          :func:`read_feasibility_csv` reads it
``feasibility_json``  ``feasibility_json.schema.json``    ``feasibility.json`` of a map (``cfdesign.feasibility/1``)
``log``               ``log.schema.json``                 a recorded run's ``.npz`` (``cfdesign.log/1``) as
                                                          :func:`log_json` reads it
``log_csv``           ``log_csv.schema.json``             one row of a CSV log as :func:`read_log_csv_rows`
                                                          reads it
``candidates``        ``candidates.schema.json``          ``candidates.json`` of an automatic design
                                                          (``cfdesign.candidates/1``)
``validation``        ``validation.schema.json``          ``validation.json`` of an automatic design's
                                                          validation (``cfdesign.validation/1``)
====================  ==================================  ====================================================

The files are the contract (other tools read them with any JSON Schema validator);
:func:`validate` applies one and adds the few checks JSON Schema cannot state (a
schedule's matrices are nodes x steps, a map's point count is the product of its
grids).  :func:`validate_output` validates what a command wrote, file by file::

    from studies import schemas
    schemas.validate_output(out)          # results.json, schedule.json, feasibility.csv/json in out
    schemas.validate("study", results)    # an object in memory

Validation needs ``jsonschema>=4`` (the ``test`` extra); :func:`load` and
:func:`read_feasibility_csv` do not.
"""
from __future__ import annotations

import csv
import functools
import json
import math
import re
from importlib import resources
from pathlib import Path
from typing import Any, Iterator

from designer.validation import InputError

__all__ = ["SCHEMAS", "FILES", "DECIMAL", "decimal", "load", "validate", "read_feasibility_csv", "validate_output",
           "log_json", "read_log_csv_rows", "validate_log"]

# schema name -> its file in this package
SCHEMAS: dict[str, str] = {
    "study": "study.schema.json",
    "schedule": "schedule.schema.json",
    "feasibility": "feasibility.schema.json",
    "feasibility_json": "feasibility_json.schema.json",
    "log": "log.schema.json",
    "log_csv": "log_csv.schema.json",
    "candidates": "candidates.schema.json",
    "validation": "validation.schema.json",
}

# output file name -> the schema it follows (feasibility.csv: each of its rows)
FILES: dict[str, str] = {
    "results.json": "study",
    "schedule.json": "schedule",
    "feasibility.csv": "feasibility",
    "feasibility.json": "feasibility_json",
    "candidates.json": "candidates",
    "validation.json": "validation",
}

# A number in a CSV file the commands read (a log, feasibility.csv): decimal notation only, digits with one optional
# sign, point and exponent; not Python's float() grammar (no "_", hex, inner whitespace, nan or inf).
DECIMAL = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")


def decimal(text: str) -> float | None:
    """``text`` (without surrounding whitespace) as a float when it is a decimal number (:data:`DECIMAL`: ``1``,
    ``-0.5``, ``.5``, ``2.``, ``1e-3``), else None (``1_0``, ``0x1p3``, ``1 0``, ``nan``, ``inf``)."""
    return float(text) if DECIMAL.fullmatch(text) else None


_INTEGER_COLUMNS = ("feasible", "theorem2", "iterations", "better_than_local")
_TEXT_COLUMNS = ("binding", "verdict", "rule")
_MAX_MESSAGE = 240  # characters of a validator message (they quote the offending value)


def load(name: str) -> dict:
    """The schema ``name`` (a key of :data:`SCHEMAS`) as a fresh dict, read from the package data."""
    if name not in SCHEMAS:
        raise InputError(f"unknown schema {name!r}; schemas: {', '.join(SCHEMAS)}")
    return json.loads(resources.files(__name__).joinpath(SCHEMAS[name]).read_text(encoding="utf-8"))


@functools.lru_cache(maxsize=None)
def _validator(name: str):
    try:
        import jsonschema
    except ImportError:  # pragma: no cover - jsonschema is in the test extra
        raise InputError("validating against the schemas needs jsonschema>=4 (pip install 'cfdesign[test]')") from None
    return jsonschema.Draft202012Validator(load(name))


_IDENTIFIER = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


def _json_path(parts) -> str:
    """``$.a[0]['b c']``: the JSONPath of ``parts`` (written as jsonschema writes it)."""
    out = "$"
    for p in parts:
        if isinstance(p, int):
            out += f"[{p}]"
        elif _IDENTIFIER.match(p):
            out += f".{p}"
        else:
            out += "['" + p.replace("\\", "\\\\").replace("'", "\\'") + "']"
    return out


def _shorten(message: str) -> str:
    return message if len(message) <= _MAX_MESSAGE else message[:_MAX_MESSAGE] + " ..."


def validate(name: str, obj: Any, *, what: str | None = None) -> None:
    """Check ``obj`` against schema ``name``; raise :class:`~designer.validation.InputError` on the first error.

    Parameters
    ----------
    name : str
        A key of :data:`SCHEMAS` (``"feasibility"``: one row of ``feasibility.csv``).
    obj
        The parsed JSON (or CSV row) to check.
    what : str, optional
        What ``obj`` is, for the message (default: the schema's name).

    Raises
    ------
    InputError
        ``"<what> does not follow schema <name> (<file>): <JSON path>: <message>"`` for the
        first error (jsonschema's best match: the most specific error at the earliest path), or
        for the first failed check of the shapes the schema cannot state.
    """
    if name not in SCHEMAS:
        raise InputError(f"unknown schema {name!r}; schemas: {', '.join(SCHEMAS)}")
    validator = _validator(name)
    from jsonschema.exceptions import best_match

    error = best_match(validator.iter_errors(obj))
    found = None if error is None else (list(error.absolute_path), error.message)
    if found is None:
        found = next(_SHAPE_CHECKS.get(name, _no_checks)(obj), None)
    if found is not None:
        path, message = found
        raise InputError(f"{what or name} does not follow schema {name!r} ({SCHEMAS[name]}): "
                         f"{_json_path(path)}: {_shorten(message)}")


# ----------------------------------------------------------------------------------- what JSON Schema cannot state
# Each check runs on an object that the schema accepted and yields (path, message) per failure.
def _no_checks(obj) -> Iterator[tuple[list, str]]:
    return iter(())


def _matrix_shape(value, rows: int, cols: int, path: list, label: str) -> Iterator[tuple[list, str]]:
    if len(value) != rows:
        yield path, f"{label} has {len(value)} rows, expected {rows}"
        return
    for i, row in enumerate(value):
        if len(row) != cols:
            yield path + [i], f"row {i} of {label} has {len(row)} entries, expected {cols}"
            return


def _schedule_shapes(obj: dict) -> Iterator[tuple[list, str]]:
    import rules

    rule = rules.find(obj["mode"])
    if rule is None:
        yield ["mode"], f"{obj['mode']!r} is not a gain rule ({rules.choices()})"
    record = obj.get("gain_rule")
    if rule is not None and record is not None:
        for key in ("name", "runtime", "deployable"):
            if record[key] != getattr(rule, key):
                yield ["gain_rule", key], f"{record[key]!r}, but gain rule {rule.name!r} has {getattr(rule, key)!r}"
    mode = (obj.get("options") or {}).get("mode")
    if isinstance(mode, str) and mode not in rules.names():
        yield ["options", "mode"], f"{mode!r} is not a gain rule ({rules.choices()})"
    nodes, steps = obj["nodes"], obj["steps"]
    for key in ("sigma", "beta", "trace_bound"):
        yield from _matrix_shape(obj[key], nodes, steps, [key], f"{key} (nodes x steps)")
    for i, v in enumerate(obj["violations"]):
        if v["node"] >= nodes:
            yield ["violations", i, "node"], f"node {v['node']} of a network of {nodes} nodes"
        if v["step"] > steps:
            yield ["violations", i, "step"], f"step {v['step']} of a run of {steps} steps"
    cond = obj.get("conditioning")
    if isinstance(cond, dict):
        kappa, where = cond["gain_condition"], cond["gain_condition_step"]
        for key, value in (("gain_condition", kappa), ("gain_condition_step", where)):
            if value is not None and len(value) != nodes:
                yield ["conditioning", key], f"{len(value)} entries for a network of {nodes} nodes"
                return
        for j, i in enumerate(cond["ill_conditioned"]):
            if i >= nodes or kappa is None or kappa[i] is None or not kappa[i] > cond["threshold"]:
                yield ["conditioning", "ill_conditioned", j], (f"node {i} is not one whose gain condition number "
                                                               f"exceeds the threshold {cond['threshold']:g}")
        for i, v in enumerate(kappa or []):
            if v is not None and v > cond["threshold"] and i not in cond["ill_conditioned"]:
                yield ["conditioning", "gain_condition", i], (f"node {i}'s gain condition number {v:g} exceeds the "
                                                              "threshold but the node is not listed as ill-conditioned")
            if v is not None and where is not None and (where[i] is None or where[i] >= steps):
                yield ["conditioning", "gain_condition_step", i], f"step {where[i]} of a run of {steps} steps"
    detail = obj["verdict_detail"]
    if detail["verdict"] != obj["verdict"]:
        yield ["verdict_detail", "verdict"], f"{detail['verdict']!r} but the file's verdict is {obj['verdict']!r}"
    for key in ("bounded", "growing", "bounded_reason"):
        if detail[key] != obj[key]:
            yield ["verdict_detail", key], f"{detail[key]!r} but the file's {key} is {obj[key]!r}"
    if detail["horizon"] is not None and detail["horizon"] != steps:
        yield ["verdict_detail", "horizon"], f"horizon {detail['horizon']} of a run of {steps} steps"
    for key in ("final_trace", "local", "ratio_open_loop", "ratio_centralized", "ratio_local", "max_ratio_open_loop",
                "growth"):
        if detail[key] is not None and len(detail[key]) != nodes:
            yield ["verdict_detail", key], f"{len(detail[key])} entries for a network of {nodes} nodes"
    for j, i in enumerate(detail["nodes"]):
        if i >= nodes:
            yield ["verdict_detail", "nodes", j], f"node {i} of a network of {nodes} nodes"
    if "U" in obj and "state_names" in obj:
        n = len(obj["state_names"])
        yield from _matrix_shape(obj["U"], n, n, ["U"], "U (n_x x n_x)")
    if "V" in obj and "sensors" in obj:
        if len(obj["V"]) != len(obj["sensors"]):
            yield ["V"], f"{len(obj['V'])} matrices for {len(obj['sensors'])} sensors"
            return
        for i, (v, s) in enumerate(zip(obj["V"], obj["sensors"])):
            yield from _matrix_shape(v, s["dim"], s["dim"], ["V", i], f"V of sensor {s['name']!r} (n_z x n_z)")


def _feasibility_json_shapes(obj: dict) -> Iterator[tuple[list, str]]:
    names = [g["name"] for g in obj["grids"]]
    for i, n in enumerate(names):
        if n in names[:i]:
            yield ["grids", i, "name"], f"grid parameter {n!r} given twice"
    expected = math.prod(len(g["values"]) for g in obj["grids"])
    if obj["points"] != expected:
        yield ["points"], f"{obj['points']} points, but the grids have {expected}"
    if obj["feasible_points"] > obj["points"]:
        yield ["feasible_points"], f"{obj['feasible_points']} feasible points of {obj['points']}"
    counts = obj["verdicts"]
    if sum(counts.values()) != obj["points"]:
        yield ["verdicts"], f"{sum(counts.values())} verdicts for {obj['points']} points"
    if counts["certified"] + counts["vacuous"] < obj["feasible_points"]:
        yield ["verdicts"], (f"{counts['certified']} certified and {counts['vacuous']} vacuous points, but "
                             f"{obj['feasible_points']} feasible ones (a fixed point is one or the other)")
    picked = [c["picked_points"] for c in obj.get("candidates") or []]
    if picked and sum(picked) != obj["points"]:
        yield ["candidates"], f"{sum(picked)} points picked for {obj['points']} points"
    failed = obj.get("failed_points", 0)
    if isinstance(failed, int) and obj["feasible_points"] + failed > obj["points"]:
        yield ["failed_points"], f"{failed} failed and {obj['feasible_points']} feasible points of {obj['points']}"


def _log_shapes(obj: dict) -> Iterator[tuple[list, str]]:
    K = len(obj["z"])
    widths = {len(r) for r in obj["z"]}
    if len(widths) > 1:
        yield ["z"], f"rows of {sorted(widths)} components: every row must have n_z"
    for key, rows in (("inputs", K), ("uplink", K), ("x", K + 1), ("channel_dos", K), ("channel_fdi", K),
                      ("channel_xi", K)):
        if key in obj and len(obj[key]) != rows:
            yield [key], f"{len(obj[key])} entries along its first axis, expected {rows} (z has {K} steps)"
            return
    if "uplink" in obj and obj["z"] and obj["uplink"] and len(obj["uplink"][0]) != len(obj["z"][0]):
        yield ["uplink"], f"{len(obj['uplink'][0])} components per step, z has {len(obj['z'][0])}"
    n = None
    for key in ("channel_dos", "channel_fdi", "channel_xi"):
        for k, step in enumerate(obj.get(key, [])):
            if n is None:
                n = len(step)
            if len(step) != n or any(len(row) != n for row in step):
                yield [key, k], f"not N x N with N = {n} nodes"
                return
    if "channel_dos" in obj and "channel_fdi" in obj:
        for k, (d, f) in enumerate(zip(obj["channel_dos"], obj["channel_fdi"])):
            for i, (dr, fr) in enumerate(zip(d, f)):
                for j, (a, b) in enumerate(zip(dr, fr)):
                    if a and b:
                        yield ["channel_fdi", k, i, j], "a packet marked both lost (channel_dos) and falsified"
                        return


_SHAPE_CHECKS = {"schedule": _schedule_shapes, "feasibility_json": _feasibility_json_shapes, "log": _log_shapes}


# ------------------------------------------------------------------------------------------------ the files
def _cell(column: str, text: str):
    """A CSV cell as a JSON value: empty -> None, numbers -> int or float (finite), anything else its text."""
    if text == "":
        return None
    if column in _TEXT_COLUMNS:
        return text
    if column in _INTEGER_COLUMNS and re.fullmatch(r"[+-]?[0-9]{1,18}", text):
        return int(text)
    value = decimal(text.strip())
    return value if value is not None and math.isfinite(value) else text  # not a number: text, the schema refuses


def read_feasibility_csv(path) -> list[dict]:
    """The rows of a ``feasibility.csv`` as dicts of typed values (see ``feasibility.schema.json``).

    Grid parameters and ``trace_bound`` become floats, ``feasible``, ``theorem2`` and
    ``iterations`` ints, an empty cell None, ``binding`` stays text; a cell that is not a
    finite number is left as its text, so that validation names it.
    """
    return _csv_rows(path, _cell)


def _csv_rows(path, cell) -> list[dict]:
    """The rows of the CSV file ``path`` as dicts, each cell converted by ``cell(column, text)``; a row with another
    number of cells than the header is an error naming its line."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{str(path)!r} does not exist")
    with path.open(newline="", encoding="utf-8-sig") as fh:  # skips a UTF-8 BOM (as spreadsheets write)
        reader = csv.DictReader(fh, restkey="\0extra", restval="\0missing")
        if not reader.fieldnames:
            raise InputError(f"{path.name} has no header row")
        rows = []
        for row in reader:
            if "\0extra" in row or "\0missing" in row.values():
                raise InputError(f"{path.name} line {reader.line_num}: {len(reader.fieldnames)} columns in the "
                                 "header, another number in this row")
            rows.append({k: cell(k, v) for k, v in row.items()})
    return rows


def log_json(path) -> dict:
    """A recorded run's ``.npz`` (schema ``log``) as a JSON object: each array as nested lists, NaN as null, a 0-d
    array as its value (``schema`` a string, ``seed`` and ``run`` integers)."""
    import zipfile

    import numpy as np

    import studies.memory as memory

    path = Path(path)
    if not path.is_file():
        raise InputError(f"{str(path)!r} does not exist")
    if not zipfile.is_zipfile(path):
        raise InputError(f"{str(path)!r} is not an .npz archive")
    with zipfile.ZipFile(path) as zf:  # the arrays' decompressed sizes, from the directory, before any is read
        stored = sum(info.file_size for info in zf.infolist())
    # each number becomes a Python object in a list: about 32 bytes (a float object and its pointer) per 8 stored
    memory.check(memory.Need("validating a log", ((memory.Part(f"log {path} as JSON", 5.0 * stored,
                                                              f"{stored} bytes of arrays", "a shorter log"),),)))
    with np.load(path, allow_pickle=False) as d:
        out = {}
        for k in d.files:
            a = d[k]
            if a.dtype.kind in "fc":
                out[k] = np.where(np.isnan(a), None, a.astype(object)).tolist()
            else:
                out[k] = a.tolist()
    return out


def _log_cell(column: str, text: str):
    text = text.strip()  # as studies.recorded.read_log_csv reads a cell
    if text != "" and (column in ("step", "sensor") or column.startswith("from_")):
        return int(text) if re.fullmatch(r"[0-9]{1,18}", text) else text
    return _cell(column, text)


def read_log_csv_rows(path) -> list[dict]:
    """The rows of a CSV log as dicts of typed values (see ``log_csv.schema.json``): ``step``, ``sensor`` and the
    ``from_J`` flags 0/1 ints, the other numbers floats, an empty cell None, a falsified packet's ``f:...`` text."""
    return _csv_rows(path, _log_cell)


def validate_log(path) -> None:
    """Validate a recorded run against its schema: an ``.npz`` as a whole (``log``), a ``.csv`` row by row
    (``log_csv``; the message names the row and its line)."""
    path = Path(path)
    if path.suffix.lower() == ".csv":
        for i, row in enumerate(read_log_csv_rows(path)):
            validate("log_csv", row, what=f"{path.name} row {i} (line {i + 2})")
    else:
        validate("log", log_json(path), what=path.name)


def _read_json(path: Path):
    def no_constant(token):
        raise InputError(f"{path.name} holds {token}, which is not JSON (write null)")

    try:
        return json.loads(path.read_text(encoding="utf-8"), parse_constant=no_constant)
    except json.JSONDecodeError as exc:
        raise InputError(f"{path.name} is not valid JSON: {exc}") from None


def validate_output(path) -> list[Path]:
    """Validate what a command wrote: one of the files of :data:`FILES`, or every one of them in a directory.

    ``feasibility.csv`` is validated row by row (the message names the row and its line).
    Returns the files validated; raises :class:`~designer.validation.InputError` on the first
    error, or when a directory holds none of the files.
    """
    path = Path(path)
    if path.is_dir():
        files = [path / f for f in FILES if (path / f).is_file()]
        if not files:
            raise InputError(f"{str(path)!r} holds none of {', '.join(FILES)}")
    elif path.name in FILES:
        if not path.is_file():
            raise InputError(f"{str(path)!r} does not exist")
        files = [path]
    else:
        raise InputError(f"{path.name!r} has no schema; files with one: {', '.join(FILES)}")
    for f in files:
        name = FILES[f.name]
        if f.suffix == ".csv":
            for i, row in enumerate(read_feasibility_csv(f)):
                validate(name, row, what=f"{f.name} row {i} (line {i + 2})")
        else:
            validate(name, _read_json(f), what=f.name)
    return files
