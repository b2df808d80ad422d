"""Parameter forms generated from an estimator's ``__init__`` signature and numpydoc.

The model builder shows one form per model-building method (PCA, LSF, SPLOCS, Varimax). The
forms are not written by hand: :class:`ParameterForm` reads the estimator class's
``__init__`` signature (names and defaults) and the "Parameters" section of its numpydoc
docstring (tooltips, and ``{'a', 'b'}`` choices for string options), so the panel follows
``core.models`` when parameters are added or renamed there.

Widget per parameter, from the class's declared constraints as summarised by
``cls.parameter_rule(name)`` (``("int"|"float", low, high[, allow_none])``,
``("options", choices)``, ``("bool",)``) and otherwise from the default: bool -> QCheckBox;
int -> QSpinBox (its minimum shows "auto (None)" when None is allowed); float -> QDoubleSpinBox for
ordinary magnitudes, a QLineEdit for tolerances like 1e-8; options -> QComboBox; anything else
(None, str, tuples) -> QLineEdit read back as a Python literal (empty means None). Data
parameters (the mesh graph, ``connectivity``) have no editor: the pipeline passes the training
meshes' triangles.
"""

from __future__ import annotations

import ast
import inspect
import math
import re
from typing import Any

from PySide6.QtCore import Signal
from PySide6.QtWidgets import (
    QCheckBox,
    QComboBox,
    QDoubleSpinBox,
    QFormLayout,
    QLineEdit,
    QSpinBox,
    QWidget,
)

_SECTION_UNDERLINE = re.compile(r"^\s*-{3,}\s*$")
_CHOICES = re.compile(r"\{([^}]*)\}")


def parse_numpydoc_parameters(doc: str | None) -> dict[str, tuple[str, str]]:
    """Map each parameter of a numpydoc "Parameters" section to ``(type, description)``.

    ``"a, b : float"`` entries give both names the same text. Returns an empty dict if the
    docstring has no such section.
    """
    if not doc:
        return {}
    lines = inspect.cleandoc(doc).splitlines()
    start = None
    for i in range(len(lines) - 1):
        if lines[i].strip() == "Parameters" and _SECTION_UNDERLINE.match(lines[i + 1]):
            start = i + 2
            break
    if start is None:
        return {}
    entries: dict[str, tuple[str, str]] = {}
    names: list[str] = []
    kind = ""
    text: list[str] = []

    def flush() -> None:
        for name in names:
            entries[name] = (kind, " ".join(text).strip())

    for i in range(start, len(lines)):
        line = lines[i]
        if i + 1 < len(lines) and _SECTION_UNDERLINE.match(lines[i + 1]) and line.strip():
            break  # next section header
        if line and not line[0].isspace():
            flush()
            head, _, kind = line.partition(":")
            names = [n.strip().lstrip("*") for n in head.split(",") if n.strip()]
            kind = kind.strip()
            text = []
        elif line.strip():
            text.append(line.strip())
    flush()
    return entries


def _choices_from_type(kind: str) -> list[str] | None:
    """``"{'sync', 'gpa'}, default='sync'"`` -> ``['sync', 'gpa']``."""
    match = _CHOICES.search(kind)
    if not match:
        return None
    options = [o.strip().strip("'\"") for o in match.group(1).split(",")]
    options = [o for o in options if o and o != "None"]
    return options or None


def _float_decimals(value: float) -> int:
    if value == 0 or not math.isfinite(value):
        return 4
    return int(min(10, max(3, 3 - math.floor(math.log10(abs(value))))))


class ParameterForm(QWidget):
    """A QFormLayout of editors for the keyword parameters of ``cls.__init__``.

    Parameters
    ----------
    cls : type
        Estimator class (scikit-learn style: every parameter in ``__init__`` with a default).
    skip : iterable of str
        Parameter names not to show (set by the panel itself).
    parent : QWidget, optional
    """

    changed = Signal()

    def __init__(self, cls: type, skip: tuple[str, ...] = (), parent: QWidget | None = None):
        super().__init__(parent)
        self.cls = cls
        self._editors: dict[str, QWidget] = {}
        self._defaults: dict[str, Any] = {}
        self._rules: dict[str, tuple | None] = {}
        docs = parse_numpydoc_parameters(cls.__doc__)
        if not docs:
            docs = parse_numpydoc_parameters(cls.__init__.__doc__)
        layout = QFormLayout(self)
        layout.setContentsMargins(0, 0, 0, 0)
        settings = getattr(cls, "setting_names", None)
        settings = set(settings()) if settings else None  # data (the mesh graph) has no editor
        for name, param in inspect.signature(cls.__init__).parameters.items():
            if name == "self" or name in skip or param.kind in (param.VAR_POSITIONAL,
                                                                 param.VAR_KEYWORD) or \
                    (settings is not None and name not in settings):
                continue
            default = None if param.default is inspect.Parameter.empty else param.default
            kind, description = docs.get(name, ("", ""))
            rule = cls.parameter_rule(name) if hasattr(cls, "parameter_rule") else None
            editor = self._make_editor(default, kind, rule)
            tooltip = f"<b>{name}</b>"
            if kind:
                tooltip += f" : {kind}"
            if description:
                tooltip += f"<br>{description}"
            tooltip += f"<br><i>default: {default!r}</i>"
            editor.setToolTip(tooltip)
            editor.setObjectName(f"param_{name}")
            self._editors[name] = editor
            self._defaults[name] = default
            self._rules[name] = rule
            layout.addRow(name.rstrip("_").replace("_", " "), editor)
            layout.labelForField(editor).setToolTip(tooltip)

    # -- editors ---------------------------------------------------------------------------

    def _make_editor(self, default: Any, kind: str, rule: tuple | None) -> QWidget:
        rule_kind = rule[0] if rule else None
        low = rule[1] if rule and rule_kind in ("int", "float") else None
        high = rule[2] if rule and rule_kind in ("int", "float") else None
        allow_none = bool(rule and rule_kind in ("int", "float") and len(rule) > 3 and rule[3])
        choices = list(rule[1]) if rule_kind == "options" else _choices_from_type(kind)
        if isinstance(default, bool) or rule_kind == "bool":
            editor = QCheckBox()
            editor.setChecked(bool(default))
            editor.toggled.connect(self.changed)
        elif (isinstance(default, int) or (default is None and rule_kind == "int")) and \
                rule_kind != "float":
            editor = QSpinBox()
            lo = int(low) if low is not None else (0 if (default or 0) >= 0 else -10**9)
            hi = int(high) if high is not None else 10**9
            if allow_none or default is None:
                lo -= 1  # the minimum stands for None
                editor.setSpecialValueText("auto (None)")
            editor.setRange(lo, hi)
            editor.setValue(lo if default is None else default)
            editor.setProperty("none_value", lo if (allow_none or default is None) else None)
            editor.valueChanged.connect(self.changed)
        elif isinstance(default, float) and 1e-3 <= abs(default) < 1e6 and not allow_none:
            editor = QDoubleSpinBox()
            decimals = _float_decimals(default)
            editor.setDecimals(decimals)
            lo = float(low) if low is not None else (0.0 if default >= 0 else -1e9)
            editor.setRange(lo, float(high) if high is not None else 1e9)
            editor.setSingleStep(10.0 ** math.floor(math.log10(abs(default))))
            editor.setValue(default)
            editor.valueChanged.connect(self.changed)
        elif choices is not None and (default is None or isinstance(default, str)):
            editor = QComboBox()
            if default is None:
                editor.addItem("None")
            editor.addItems([str(c) for c in choices])
            if isinstance(default, str) and default not in choices:
                editor.addItem(default)
            editor.setCurrentText("None" if default is None else default)
            editor.currentTextChanged.connect(self.changed)
        else:
            editor = QLineEdit("" if default is None else
                               (default if isinstance(default, str) else repr(default)))
            editor.setPlaceholderText("None (automatic)")
            editor.setProperty("string_param", isinstance(default, str))
            editor.textChanged.connect(self.changed)
        return editor

    # -- values ----------------------------------------------------------------------------

    def names(self) -> list[str]:
        return list(self._editors)

    def editor(self, name: str) -> QWidget:
        return self._editors[name]

    def values(self) -> dict[str, Any]:
        """The parameters as typed values; raises ValueError naming a malformed entry."""
        out: dict[str, Any] = {}
        for name, editor in self._editors.items():
            if isinstance(editor, QCheckBox):
                out[name] = editor.isChecked()
            elif isinstance(editor, QSpinBox):
                none_value = editor.property("none_value")
                value = int(editor.value())
                out[name] = None if none_value is not None and value == none_value else value
            elif isinstance(editor, QDoubleSpinBox):
                out[name] = float(editor.value())
            elif isinstance(editor, QComboBox):
                text = editor.currentText()
                out[name] = None if text == "None" else text
            else:
                text = editor.text().strip()
                if not text or text == "None":
                    out[name] = None
                elif editor.property("string_param"):
                    out[name] = text
                else:
                    try:
                        out[name] = ast.literal_eval(text)
                    except (ValueError, SyntaxError):
                        raise ValueError(f"parameter '{name}': cannot read '{text}' as a "
                                         f"number or literal") from None
                    self._check_number(name, out[name])
        return out

    def _check_number(self, name: str, value: Any) -> None:
        rule = self._rules.get(name)
        if not rule or rule[0] not in ("int", "float"):
            return
        low, high = rule[1], rule[2]
        if isinstance(value, bool) or not isinstance(value, (int, float)) or \
                (low is not None and value < low) or (high is not None and value > high):
            span = f"[{'-inf' if low is None else low}, {'inf' if high is None else high}]"
            raise ValueError(f"parameter '{name}' must be a number in {span}; got {value!r}")

    def set_values(self, values: dict[str, Any]) -> None:
        for name, value in values.items():
            editor = self._editors.get(name)
            if editor is None:
                continue
            if isinstance(editor, QCheckBox):
                editor.setChecked(bool(value))
            elif isinstance(editor, QSpinBox):
                none_value = editor.property("none_value")
                editor.setValue(none_value if value is None and none_value is not None else
                                int(value or 0))
            elif isinstance(editor, QDoubleSpinBox):
                editor.setValue(float(value))
            elif isinstance(editor, QComboBox):
                editor.setCurrentText("None" if value is None else str(value))
            else:
                editor.setText("" if value is None else
                               (value if isinstance(value, str) else repr(value)))

    def reset(self) -> None:
        """Back to the estimator's defaults."""
        self.set_values(self._defaults)
