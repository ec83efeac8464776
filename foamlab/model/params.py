"""Parameters of the combined model (paper, sections 3 and 4.1), in foamlab's units.

Units (chosen so that every component takes displacement in mm and time in s):
- elastic:  k_i  [N], coefficient of (x / x_scale)^i, i = 0..P (Eq. 12 in a scaled
  variable; raw k_i in N/mm^i span ~14 decades for P = 7 and are unusable);
- damping:  a_i  [N mm^-1 s^-1] and alpha_i = sigma_i + j*omega_i [s^-1], i = 1..N
  (Eq. 9 kernel on the displacement; each complex alpha stands for a conjugate pair,
  see docs/model.md);
- residual: r_ci [N s^beta mm^-1] and beta_ci [-] for cycle c = 1..C, term i = 1..M
  (Eq. 10/11; the paper's Table 3 uses m^-1, i.e. 1000x ours), in one of two forms
  (residual_form: 'causal' Eq. 10 or 'paper' Eq. 11 in x; docs/model.md).
"""

from __future__ import annotations

import json
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from foamlab import CONFIG_DIR, FoamlabError
from foamlab.model.layout import Layout, check_form

DEFAULT_SPECIMEN = CONFIG_DIR / "specimens" / "default.toml"


@dataclass
class ModelParameters:
    x_scale_mm: float
    elastic_k: np.ndarray                      # (P+1,)  N
    damping_a: np.ndarray                      # (N,)    N/(mm s)
    damping_alpha: np.ndarray                  # (N,)    complex, 1/s
    residual_r: np.ndarray                     # (C, M)  N s^beta / mm
    residual_beta: np.ndarray                  # (C, M)
    description: str = ""
    metadata: dict = field(default_factory=dict)
    residual_form: str = "causal"              # 'causal' or 'paper' (RESIDUAL_FORMS)
    shared_orders: bool = False                # every cycle's terms have the same orders, fitted so

    def __post_init__(self) -> None:
        check_form(self.residual_form)
        self.elastic_k = np.atleast_1d(np.asarray(self.elastic_k, dtype=float))
        self.damping_a = np.atleast_1d(np.asarray(self.damping_a, dtype=float))
        self.damping_alpha = np.atleast_1d(np.asarray(self.damping_alpha, dtype=complex))
        self.residual_r = np.atleast_2d(np.asarray(self.residual_r, dtype=float))
        self.residual_beta = np.atleast_2d(np.asarray(self.residual_beta, dtype=float))
        if self.damping_a.shape != self.damping_alpha.shape:
            raise FoamlabError("model parameters: damping a and alpha differ in length")
        if self.residual_r.shape != self.residual_beta.shape:
            raise FoamlabError("model parameters: residual r and beta differ in shape")
        if not self.x_scale_mm > 0:
            raise FoamlabError("model parameters: x_scale_mm must be positive")
        if np.any(self.residual_beta >= 1.0):
            raise FoamlabError("model parameters: fractional orders beta must be < 1 (Eq. 10)")
        if self.shared_orders and not np.all(self.residual_beta == self.residual_beta[:1]):
            raise FoamlabError("model parameters: shared orders differ between cycles")

    # -- orders -----------------------------------------------------------------
    @property
    def order_P(self) -> int:
        return len(self.elastic_k) - 1

    @property
    def order_N(self) -> int:
        return len(self.damping_a)

    @property
    def order_M(self) -> int:
        return self.residual_r.shape[1]

    @property
    def n_residual_cycles(self) -> int:
        return self.residual_r.shape[0]

    @property
    def layout(self) -> Layout:
        """Where each entry of to_vector() goes when the model is fitted (linear / nonlinear)."""
        return Layout(P=self.order_P, N=self.order_N, M=self.order_M, C=self.n_residual_cycles,
                      form=self.residual_form, shared=self.shared_orders)

    def residual_terms(self, cycle: int) -> tuple[np.ndarray, np.ndarray]:
        """(r, beta) of a 1-based cycle; cycles beyond those identified reuse the last."""
        c = min(max(cycle, 1), self.n_residual_cycles) - 1
        return self.residual_r[c], self.residual_beta[c]

    # -- flat vector form (identification) -----------------------------------------
    def names(self) -> list[str]:
        n = [f"k{i}" for i in range(self.order_P + 1)]
        for i in range(self.order_N):
            n += [f"a{i+1}", f"alpha{i+1}_re", f"alpha{i+1}_im"]
        for c in range(self.n_residual_cycles):
            for i in range(self.order_M):
                n += [f"r{c+1}_{i+1}", f"beta{c+1}_{i+1}"]
        return n

    def to_vector(self) -> np.ndarray:
        v = list(self.elastic_k)
        for a, al in zip(self.damping_a, self.damping_alpha):
            v += [a, al.real, al.imag]
        for c in range(self.n_residual_cycles):
            for r, b in zip(self.residual_r[c], self.residual_beta[c]):
                v += [r, b]
        return np.asarray(v, dtype=float)

    def with_vector(self, v) -> "ModelParameters":
        v = np.asarray(v, dtype=float)
        p1, n, c, m = self.order_P + 1, self.order_N, self.n_residual_cycles, self.order_M
        if len(v) != p1 + 3 * n + 2 * c * m:
            raise ValueError("parameter vector has the wrong length")
        d = v[p1:p1 + 3 * n].reshape(n, 3)
        res = v[p1 + 3 * n:].reshape(c, m, 2)
        return ModelParameters(
            x_scale_mm=self.x_scale_mm,
            elastic_k=v[:p1],
            damping_a=d[:, 0],
            damping_alpha=d[:, 1] + 1j * d[:, 2],
            residual_r=res[:, :, 0],
            residual_beta=res[:, :, 1],
            description=self.description,
            metadata=dict(self.metadata),
            residual_form=self.residual_form,
            shared_orders=self.shared_orders,
        )

    # -- files --------------------------------------------------------------------
    def to_dict(self) -> dict:
        return {
            "x_scale_mm": float(self.x_scale_mm),
            "description": self.description,
            "elastic": {"k": [float(k) for k in self.elastic_k]},
            "damping": {
                "a": [float(a) for a in self.damping_a],
                "alpha_re": [float(a.real) for a in self.damping_alpha],
                "alpha_im": [float(a.imag) for a in self.damping_alpha],
            },
            "residual": {
                "form": self.residual_form,
                "shared_orders": self.shared_orders,
                "r": [[float(x) for x in row] for row in self.residual_r],
                "beta": [[float(x) for x in row] for row in self.residual_beta],
            },
        }

    @classmethod
    def from_dict(cls, d: dict) -> "ModelParameters":
        try:
            if "model" not in d and isinstance(d.get("parameters"), dict):  # `foamlab fit --json`
                return cls.from_fit_parameters(d["parameters"], d.get("form", "causal"))
            if "model" in d and isinstance(d["model"], dict):  # a fit result file
                d = d["model"]
            dmp, res = d["damping"], d["residual"]
            return cls(
                x_scale_mm=float(d["x_scale_mm"]),
                elastic_k=d["elastic"]["k"],
                damping_a=dmp["a"],
                damping_alpha=np.asarray(dmp["alpha_re"], float) + 1j * np.asarray(dmp["alpha_im"], float),
                residual_r=res["r"],
                residual_beta=res["beta"],
                description=d.get("description", ""),
                residual_form=str(res.get("form", "causal")),
                shared_orders=bool(res.get("shared_orders", False)),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise FoamlabError(f"model parameters: missing or malformed entry ({exc})") from None

    @classmethod
    def from_fit_parameters(cls, parameters: dict, form: str = "causal") -> "ModelParameters":
        """From the "parameters" object of `foamlab fit --json` (name -> {value, stderr}):
        the flat names of names() plus x_scale_mm; the orders follow from the names; `form`
        is the JSON's "form"."""
        try:
            v = {str(k): float(e["value"] if isinstance(e, dict) else e) for k, e in parameters.items()}
            P = max(int(k[1:]) for k in v if re.fullmatch(r"k\d+", k))
            N = max([int(k[1:]) for k in v if re.fullmatch(r"a\d+", k)], default=0)
            cm = [tuple(map(int, m.groups())) for k in v if (m := re.fullmatch(r"r(\d+)_(\d+)", k))]
            C, M = (max(c for c, _ in cm), max(i for _, i in cm)) if cm else (1, 0)
            return cls(
                x_scale_mm=v["x_scale_mm"],
                elastic_k=[v[f"k{i}"] for i in range(P + 1)],
                damping_a=[v[f"a{i}"] for i in range(1, N + 1)],
                damping_alpha=[v[f"alpha{i}_re"] + 1j * v[f"alpha{i}_im"] for i in range(1, N + 1)],
                residual_r=np.array([[v[f"r{c}_{i}"] for i in range(1, M + 1)] for c in range(1, C + 1)]).reshape(C, M),
                residual_beta=np.array([[v[f"beta{c}_{i}"] for i in range(1, M + 1)]
                                        for c in range(1, C + 1)]).reshape(C, M),
                residual_form=str(form),
                shared_orders=any(isinstance(e, dict) and e.get("same_as") for e in parameters.values()),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise FoamlabError(f"model parameters: fit result incomplete or malformed ({exc})") from None

    @classmethod
    def load(cls, path: str | Path) -> "ModelParameters":
        """Read a specimen TOML (configs/specimens) or a fit result / parameter JSON."""
        path = Path(path)
        if not path.is_file():
            raise FoamlabError(f"specimen file not found: {path}")
        try:
            if path.suffix.lower() == ".toml":
                d = tomllib.loads(path.read_text(encoding="utf-8"))
            else:
                d = json.loads(path.read_text(encoding="utf-8"))
        except (tomllib.TOMLDecodeError, json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise FoamlabError(f"{path}: not a valid specimen file ({exc})") from None
        return cls.from_dict(d)

    @classmethod
    def default(cls) -> "ModelParameters":
        """The documented default specimen (configs/specimens/default.toml)."""
        return cls.load(DEFAULT_SPECIMEN)
