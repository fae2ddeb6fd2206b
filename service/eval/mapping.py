"""Label -> traversability ground truth, from a YAML file per dataset."""

from __future__ import annotations

from importlib import resources
from pathlib import Path

import numpy as np
import yaml
from gcdtrav.service.eval.datasets import DatasetError
from numpy.typing import NDArray

IGNORE = "ignore"


def load_mapping(source: Path | str, class_names: dict[int, str]) -> NDArray[np.float32]:
    """A lookup table: class id -> traversability, NaN for ignored classes.

    ``source`` is a YAML file or the name of a shipped mapping ('goose', 'rugd'). Every class of the
    dataset must be mapped and every mapped name must be a class: a typo would silently drop pixels.
    """
    if isinstance(source, str) and not source.endswith((".yaml", ".yml")):
        text = resources.files("gcdtrav.service.eval").joinpath(f"data/{source}.yaml").read_text("utf-8")
        where = f"built-in mapping '{source}'"
    else:
        where = str(source)
        try:
            text = Path(source).read_text("utf-8")
        except OSError as err:
            raise DatasetError(f"{where}: cannot read the mapping: {err}") from None
    data = yaml.safe_load(text)
    if not isinstance(data, dict) or not isinstance(data.get("classes"), dict):
        raise DatasetError(f"{where}: expected 'classes:' with one 'name: value-or-ignore' per class")
    mapping: dict[str, object] = data["classes"]
    known = set(class_names.values())
    problems = [f"'{name}' is not a class of this dataset" for name in mapping if name not in known]
    problems += [
        f"class '{name}' has no value (a number in [0, 1] or 'ignore')" for name in sorted(known) if name not in mapping
    ]
    for name, value in mapping.items():
        if value != IGNORE and not (isinstance(value, int | float) and 0.0 <= float(value) <= 1.0):
            problems.append(f"'{name}': {value!r} is neither a number in [0, 1] nor 'ignore'")
    if problems:
        raise DatasetError(f"{where}: " + "; ".join(problems))
    size = max(class_names) + 1
    table = np.full(size, np.nan, dtype=np.float32)
    for index, name in class_names.items():
        value = mapping[name]
        if value != IGNORE:
            table[index] = float(value)  # type: ignore[arg-type]
    return table


def ground_truth(ids: NDArray[np.int32], table: NDArray[np.float32]) -> NDArray[np.float32]:
    """Traversability per pixel; NaN for ignored classes and ids outside the table."""
    valid = (ids >= 0) & (ids < len(table))
    values = np.full(ids.shape, np.nan, dtype=np.float32)
    values[valid] = table[ids[valid]]
    return values
