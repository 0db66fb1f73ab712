#!/usr/bin/env python3
"""Peer benchmark of `hbmu update boards` (step 1) against PyMC's SMC on the same exported ROM
and the same data (issue 9, acceptance point "Peer, in benches/, not CI").

What it does
------------
1. Step 1 with hbmu (unless --hbmu-out names an existing output directory): runs
   ``hbmu update boards WORK/ingest WORK/pair --extract WORK/extract --particles DRAWS
   --runs CHAINS --rom-basis 30 --no-shapes --board-coordinates natural --sigma-prior half-normal
   --no-model-error --threads CORES
   --out OUT/hbmu --force`` (the paper's coordinates, which the PyMC model below writes)
   under ``/usr/bin/time`` (wall, user, system seconds, max RSS). ``--boards N`` updates the
   first N boards only (``--hold-out`` the rest) and ``--eps-fixed V`` fixes ε of every mode
   in both tools: smaller, wider posteriors, to find one that PyMC's SMC converges on, so that
   the posteriors can be compared where it does.
2. Builds the same step-1 posterior in PyMC 5 from what that run exported and read:
   ``rom.npz`` (the reduced K(θ) = Σ c_i(θ) K_i, M(θ) = Σ d_j(θ) M_j and the coefficient map in
   ``meta_json``: CoreQ, Linear and Coupling terms, src/fem/npz.rs, src/fem/params.rs,
   src/fem/laminate.rs), ``pair/pairs.parquet`` + ``pair/presence.parquet`` (the paired
   free-free modes; the labels pair marks for updating, or the manifest's ``modes``) and
   ``ingest/masses.parquet``; the priors are read from hbmu's manifest config
   (``prior_width``, ``sigma_scale``, ``lkj_eta``, ``eps``), so both tools run one posterior:

   - per board t, x_t = θ_t/θ_nominal − 1 for θ = (e_x_pa, e_y_pa, g_xy_pa, mass_scale);
     x_t = μ + diag(σ) L_Ω z_t, z_t ~ N(0, I) (non-centred);
   - μ_k ~ N(0, prior_width²); σ_k ~ HalfNormal(sigma_scale); Ω ~ LKJ(η)
     (``pm.LKJCholeskyCov`` with ``sd_dist = HalfNormal``);
   - ε_m (relative eigenvalue error of mode label m) ~ LogNormal(ln median, log_sd²);
   - eigenvalue terms λ̂_rm ~ N(λ_m(θ_t), (ε_m λ̂_rm)²), λ = (2π f)², one per accepted
     free-free pair of an updated label (src/bayes/modal.rs ``log_lik``);
   - mass terms m̂_t ~ N(m_nom (1 + x_t,mass_scale), s_t²), s_t² = std²/n_stable +
     resolution²/12 (std² if ingest flagged the readings inconsistent), s_t floored at
     2e-4 m̂_t (src/stage/update.rs ``mass_obs``);
   - the forward model: a pytensor ``Op`` (no gradient; SMC needs none) that forms K_r(θ_t)
     for all boards, solves the reduced eigenproblem with ``numpy.linalg.eigh`` (M_r = d₀ I:
     the basis is M₀-orthonormal and the mass has one term, as in hbmu's hot path), and
     tracks the labels by overlap with the reference shapes at the ROM centre exactly as
     ``assign_labels`` does (greedy by |yᵀr|/‖y‖, 1/√2 rule and the veering rule); a lost
     label or inadmissible parameters give log L = −∞ (a ``pm.Potential``), as in hbmu.

3. Checks, before sampling, that it is the same posterior:
   (a) forward model: the posterior-predictive mean and sd of every updated mode's frequency
       at hbmu's own draws (boards.parquet, the draws ``residuals`` uses: every
       max(1, particles // 250)-th particle of each run) against ``residuals.parquet``;
   (b) likelihood: the PyMC model's compiled log-likelihood (``model.datalogp``) at hbmu's
       draws (x_t from boards.parquet, ε from population.parquet) against a line-by-line
       NumPy transcription of ``modal::log_lik``. hbmu writes no per-draw log-likelihood,
       so (b) checks the PyMC graph, (a) the ROM, the tracking and the data selection, and
       the log evidence (below) the normalising constants.
   After sampling, (c): the PyMC model's own log posterior density (``model.logp()``, its
   value variables' Jacobians included) and log-likelihood at 400 of hbmu's draws and at 400
   of PyMC's final particles: where PyMC's particles sit far below hbmu's draws in PyMC's own
   density, PyMC has not found the posterior mass (a sampler failure, not a model difference).
4. Runs ``pm.sample_smc`` (``--kernel IMH``, PyMC's default, or ``MH``) with DRAWS particles ×
   CHAINS chains on CORES processes, timed.
5. For both posteriors: ArviZ rank-normalised R-hat and bulk ESS (chain = run / chain,
   draw = particle) of every hyperparameter: mu_<p>, sigma_<p> (units of p), corr_<p>_<q>,
   eps_<label>, as hbmu's population.parquet writes them; the slowest hyperparameter is the
   one with the lowest bulk ESS; ESS/s = that ESS / wall seconds (hbmu: the whole command's
   wall time, ROM build and outputs included; PyMC: the ``sample_smc`` call, compilation and
   worker start-up included, the model build and checks excluded). Where both R-hats are
   below 1.05, posterior means are compared by z = (mean_pymc − mean_hbmu) /
   √(mcse_pymc² + mcse_hbmu²) (ArviZ ``mcse`` of the mean), for the hyperparameters and
   every board parameter; posterior sds are listed beside them.
6. Log evidence: hbmu's evidence.json (one value per run) and PyMC's
   ``sample_stats.log_marginal_likelihood`` (the last finite value per chain). Both are
   log p(data | model) with the data density in λ̂ (the −ln(ε λ̂) terms of the eigenvalue
   normals) and in grams for the masses: PyMC's is the product of the mean likelihood
   increments from exact prior draws, so the Jacobians of the unconstrained transforms and
   the prior normalisers do not enter it; hbmu tempers from a normalised Gaussian reference
   q on its unconstrained coordinates, so its prior density there carries every Jacobian
   and normaliser (normal, half-normal with its ln 2, LKJ's c_d(η), log-normal ε): both
   estimate Z = ∫ p(θ) L(θ) dθ for the same proper prior and the same data density, so the
   values are comparable. (A PyMC run that has not converged gives a biased, low Z.)

What it cannot do, and why
--------------------------
- The mode-shape terms (hbmu's default likelihood) are left out of BOTH runs (``--no-shapes``):
  rom.npz holds the basis at the FE degrees of freedom (w, ∂w/∂x, ∂w/∂y, ∂²w/∂x∂y per node)
  but not what maps it to the scan points: neither the node coordinates and the element
  interpolation (``FeModel::shape_operator`` / ``interp_row``) nor, per shape observation,
  the reduced Pᵀu and Gram matrix PᵀP (bayes::modal::ShapeObs) that hbmu builds from them.
  What an export would need (a Rust change, not made here): per free-free shape observation
  (measurement_id, label) the reduced ``pt_u`` (length r), ``n_points`` and the index of its
  r × r Gram matrix PᵀP, the distinct Gram matrices, e.g. as ``shapes_pt_u`` (n_obs, r),
  ``shapes_gram`` (n_gram, r, r) and a small table of (measurement_id, label, gram, n_points)
  in rom.npz or a ``likelihood_data.npz`` beside it; or, more generally, the interpolation
  rows of ``FeModel::shape_operator`` at every scan point (n_points × n_dof, sparse) with the
  scan points' ids, from which Pᵀu and PᵀP follow for any subset of valid points.
- The board's nominal mass m_nom (``FeModel::total_mass_kg`` at nominal, × 1e3) is not in
  rom.npz either; it is read back from boards.parquet as mass_g / mass_scale (constant over
  every row; checked). A ``nominal_mass_g`` entry in meta_json would remove the detour.

Usage
-----
    python3 benches/pymc_peer.py WORK OUT.json [--hbmu BIN | --hbmu-out DIR]
        [--draws 2000] [--chains 4] [--cores 2] [--seed 20261122] [--rom-basis 30]
        [--threshold 0.5] [--correlation-threshold 0.01] [--kernel IMH|MH]
        [--pymc-draws N] [--skip-pymc] [--scratch DIR]

WORK is a demo work directory (ingest/, pair/, extract/); OUT.json gets every number printed
and more. ``make -C pipelines bench-pymc`` runs it at the issue's size on the demo campaign.
Prints a compact table. Needs pymc ≥ 5, arviz, pyarrow, pandas.
"""

import os

# One BLAS thread per process: PyMC runs CORES worker processes, hbmu is given CORES threads.
for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import re  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import warnings  # noqa: E402

import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
import pyarrow.parquet as pq  # noqa: E402

LN_2PI = math.log(2.0 * math.pi)
SQRT_HALF = 1.0 / math.sqrt(2.0)
RHAT_OK = 1.05


# ---------------------------------------------------------------------------------------------
# The exported ROM (src/fem/npz.rs) and the forward model (src/bayes/modal.rs).


def orthotropic_q(ex, ey, g, nu):
    den = 1.0 - nu * nu * ey / ex
    return np.stack([ex / den, ey / den, nu * ey / den, g], axis=-1)


def to_mat(c):
    """[c11, c22, c12, c66] (..., 4) -> (..., 3, 3)."""
    z = np.zeros(np.shape(c)[:-1] + (3, 3))
    z[..., 0, 0] = c[..., 0]
    z[..., 1, 1] = c[..., 1]
    z[..., 0, 1] = c[..., 2]
    z[..., 1, 0] = c[..., 2]
    z[..., 2, 2] = c[..., 3]
    return z


class Rom:
    """rom.npz: K(p) = Σ c_i(p) K_i, M(p) = Σ d_j(p) M_j with the coefficient map of meta_json."""

    def __init__(self, path):
        z = np.load(path)
        self.meta = json.loads(bytes(z["meta_json"]).decode())
        self.k_terms = np.ascontiguousarray(z["k_terms"])
        self.m_terms = np.ascontiguousarray(z["m_terms"])
        self.r = self.k_terms.shape[1]
        self.names = list(self.meta["names"])
        self.nominal = np.asarray(self.meta["nominal"], float)
        self.core_idx = list(self.meta["core_idx"])
        self.n_rigid = int(self.meta["n_rigid"])
        self.n_modes = int(self.meta["n_modes"])
        ix, iy, ig, inu = self.core_idx
        self.q_nom = orthotropic_q(*(self.nominal[i] for i in (ix, iy, ig, inu)))
        self.kflat = self.k_terms.reshape(len(self.k_terms), -1)
        # M_r of a single mass term is d₀ I when the basis is M₀-orthonormal (hbmu's hot path
        # assumes it; checked here).
        self.m_identity = len(self.m_terms) == 1 and np.allclose(
            self.m_terms[0], np.eye(self.r), rtol=0, atol=1e-10
        )

    def _plan(self):
        """The K coefficients grouped by kind, so that one call evaluates them all at once."""
        core, lin, const, coup = [], [], [], []
        keys = {}
        for t, c in enumerate(self.meta["k_coefs"]):
            ((kind, a),) = c.items()
            if kind == "CoreQ":
                core.append((t, a["comp"]))
            elif kind == "Linear":
                lin.append((t, a["param"], a["scale"]))
            elif kind == "Const":
                const.append(t)
            elif kind == "Coupling":
                key = (a["h_core_m"], tuple(a["q_cu_pa"]), a["e_cu_param"], a["e_cu_nominal_pa"])
                g = keys.setdefault(key, {"s": [], "terms": []})
                if a["s_node_m"] not in g["s"]:
                    g["s"].append(a["s_node_m"])
                g["terms"].append((t, g["s"].index(a["s_node_m"]), a["comp"], a["scale"]))
            else:
                raise ValueError(f"rom.npz: unknown coefficient kind {kind}")
        arr = lambda rows, k: np.array([r[k] for r in rows])  # noqa: E731
        self._core = (arr(core, 0).astype(int), arr(core, 1).astype(int)) if core else None
        self._lin = (arr(lin, 0).astype(int), arr(lin, 1).astype(int), arr(lin, 2)) if lin else None
        self._const = np.array(const, int)
        self._coup = []
        for (h, qcu, ie, enom), g in keys.items():
            tr = g["terms"]
            self._coup.append((h, to_mat(np.asarray(qcu, float)), np.asarray(qcu, float), ie, enom,
                               np.asarray(g["s"]), arr(tr, 0).astype(int), arr(tr, 1).astype(int),
                               arr(tr, 2).astype(int), arr(tr, 3)))

    def k_coefs(self, v):
        """Coefficients c_i(p) of the K terms at parameter vectors v (B, n_params) -> (B, n_k)
        (src/fem/params.rs coefficients_unchecked)."""
        if not hasattr(self, "_core"):
            self._plan()
        ix, iy, ig, inu = self.core_idx
        q = orthotropic_q(v[:, ix], v[:, iy], v[:, ig], v[:, inu])  # (B, 4)
        out = np.empty((v.shape[0], len(self.meta["k_coefs"])))
        if self._core is not None:
            t, c = self._core
            out[:, t] = q[:, c] / self.q_nom[c][None, :]
        if self._lin is not None:
            t, p, sc = self._lin
            out[:, t] = v[:, p] / sc[None, :]
        out[:, self._const] = 1.0
        for h, qc, qcu, ie, enom, s, t, node, comp, sc in self._coup:
            # G(s; p) = ε² Q_cu (h Q_core + ε s Q_cu)⁻¹ Q_cu (laminate::coupling_kernel), at
            # every interpolation node s at once.
            eps = v[:, ie] / enom  # (B,)
            n = h * q[:, None, :] + (eps[:, None, None] * s[None, :, None]) * qcu[None, None, :]
            g = qc @ np.linalg.inv(to_mat(n)) @ qc  # (B, S, 3, 3)
            g4 = np.stack([g[..., 0, 0], g[..., 1, 1], g[..., 0, 1], g[..., 2, 2]], -1)
            out[:, t] = (eps * eps)[:, None] * g4[:, node, comp] / sc[None, :]
        return out

    def m_coefs(self, v):
        out = np.empty((v.shape[0], len(self.meta["m_coefs"])))
        for t, c in enumerate(self.meta["m_coefs"]):
            ((kind, a),) = c.items()
            if kind == "Linear":
                out[:, t] = v[:, a["param"]] / a["scale"]
            elif kind == "Const":
                out[:, t] = 1.0
            else:
                raise ValueError(f"rom.npz: unknown mass coefficient kind {kind}")
        return out

    def lowest(self, v, count):
        """The lowest `count` elastic eigenpairs at parameter vectors v (B, n_params):
        eigenvalues (B, count) and reduced vectors (B, count, r)."""
        ck = self.k_coefs(v)
        cm = self.m_coefs(v)
        a = (ck @ self.kflat).reshape(-1, self.r, self.r)
        if self.m_identity:
            w, y = np.linalg.eigh(a)
            w = w / cm[:, :1]
        else:
            import scipy.linalg as sl

            m = np.einsum("bt,tij->bij", cm, self.m_terms)
            w = np.empty((len(v), self.r))
            y = np.empty_like(a)
            for i in range(len(v)):
                w[i], y[i] = sl.eigh(a[i], m[i])
        s = slice(self.n_rigid, self.n_rigid + count)
        return w[:, s], np.swapaxes(y[:, :, s], 1, 2)


def assign_labels(refs, vectors):
    """bayes::modal::assign_labels for one unit: refs (L, r) of unit length, vectors (T, r);
    per label the index of its mode, or None where the label is lost."""
    nt = len(vectors)
    o = np.abs(refs @ vectors.T) / np.linalg.norm(vectors, axis=1)[None, :]
    best = o.argmax(axis=1)
    if len(set(best.tolist())) == len(best) and (o.max(axis=1) >= SQRT_HALF).all():
        # Distinct per-label maxima, each ≥ 1/√2: the greedy pass takes exactly these.
        return best.tolist()
    srt = -np.sort(-o, axis=1)
    top2 = [(srt[m, 0], srt[m, 1] if nt > 1 else 0.0) for m in range(len(refs))]

    def tracks(ov, m):
        if ov >= SQRT_HALF:
            return True
        a, b = top2[m]
        other = b if ov >= a else a
        return ov >= 0.5 and ov * ov + other * other >= 0.5

    pairs = sorted(
        ((o[m, j], m, j) for m in range(len(refs)) for j in range(nt)),
        key=lambda t: (-t[0], t[1], t[2]),
    )
    out = [None] * len(refs)
    done = [False] * len(refs)
    taken = [False] * nt
    for ov, m, j in pairs:
        if done[m] or taken[j]:
            continue
        done[m] = True
        if tracks(ov, m):
            taken[j] = True
            out[m] = j
    return out


class Predictor:
    """bayes::modal::ModalPredictor with step 1's Compose::Boards: θ = θ_nominal (1 + x)."""

    def __init__(self, rom, ref_modes, updated):
        self.rom = rom
        self.ref_modes = list(ref_modes)
        self.n_track = min(max(self.ref_modes) + 3, rom.n_modes)
        _, y = rom.lowest(rom.nominal[None, :], self.n_track)
        refs = y[0, self.ref_modes]
        self.refs = refs / np.linalg.norm(refs, axis=1, keepdims=True)
        self.updated = [rom.names.index(p) for p in updated]
        self.reference = rom.nominal[self.updated]
        self.nu_idx = rom.core_idx[3]

    def values(self, x):
        v = np.tile(self.rom.nominal, (x.shape[0], 1))
        v[:, self.updated] = self.reference[None, :] * (1.0 + x)
        return v

    def admissible(self, v):
        ix, iy, _, inu = self.rom.core_idx
        not_nu = np.arange(v.shape[1]) != self.nu_idx
        ok = np.all(np.isfinite(v), axis=1) & np.all((v > 0) | ~not_nu[None, :], axis=1)
        with np.errstate(all="ignore"):
            return ok & (v[:, inu] ** 2 * v[:, iy] / v[:, ix] < 1.0)

    def predict(self, x):
        """x (B, d) -> eigenvalues (B, L) in label order, and whether every label of the
        board was tracked at admissible parameters (B,)."""
        x = np.asarray(x, float)
        v = self.values(x)
        ok = self.admissible(v)
        lam = np.zeros((x.shape[0], len(self.ref_modes)))
        if not ok.any():
            return lam, ok
        vv = np.where(ok[:, None], v, self.rom.nominal[None, :])
        w, y = self.rom.lowest(vv, self.n_track)
        # assign_labels, its common case for every board at once: distinct per-label maxima
        # of the overlap, each ≥ 1/√2 (the greedy pass takes exactly these); the others
        # through the full greedy pass.
        o = np.abs(np.einsum("lr,btr->blt", self.refs, y)) / np.linalg.norm(y, axis=2)[:, None, :]
        best = o.argmax(axis=2)  # (B, L)
        srt = np.sort(best, axis=1)
        fast = (o.max(axis=2) >= SQRT_HALF).all(axis=1) & (np.diff(srt, axis=1) != 0).all(axis=1)
        rows = np.arange(len(x))[:, None]
        lam = np.where(fast[:, None], w[rows, best], 0.0)
        for b in np.flatnonzero(ok & ~fast):
            a = assign_labels(self.refs, y[b])
            if any(j is None for j in a):
                ok[b] = False
                continue
            lam[b] = w[b, a]
        lam[~ok] = 0.0
        return lam, ok


# ---------------------------------------------------------------------------------------------
# The data, as src/stage/update.rs reads it.


def load_config(hbmu_out):
    man = json.loads((hbmu_out / "update_boards.manifest.json").read_text())
    cfg = man["config"]
    # The PyMC model has neither hbmu's model-error term nor its log-normal σ prior: an hbmu
    # run with either is another posterior, so refuse it rather than compare the two.
    if cfg.get("model_error", False):
        raise SystemExit(f"{hbmu_out}: step 1 ran with the model-error term; rerun with --no-model-error")
    if cfg.get("sigma_prior", "half_normal") != "half_normal":
        raise SystemExit(f"{hbmu_out}: step 1 ran with sigma_prior {cfg['sigma_prior']}; rerun with --sigma-prior half-normal")
    if cfg.get("board_coordinates", "natural") != "natural":
        raise SystemExit(f"{hbmu_out}: step 1 ran in {cfg['board_coordinates']} coordinates; rerun with --board-coordinates natural")
    return cfg


def free_pairs(work):
    """The accepted free-free pairs with a mode, a frequency and a model mode (pairs.parquet)."""
    pairs = pq.read_table(work / "pair" / "pairs.parquet").to_pandas()
    pairs = pairs[
        pairs.accepted & pairs["mode"].notna() & pairs.freq_hz.notna() & pairs.model_mode.notna()
    ]
    return pairs[pairs.setup == "free"]


def step1_boards(free, masses):
    """Every board with a free-free pair or a weighing, sorted: the boards step 1 can update."""
    return sorted(set(free.board_id) | set(masses.index))


def select_data(work, cfg, nominal_mass_g, held_out=()):
    free = free_pairs(work)
    pres = pq.read_table(work / "pair" / "presence.parquet").to_pandas()
    chosen = list(cfg["modes"]) or list(pres[(pres.setup == "free") & pres.used_for_updating].label)
    labels, model_mode = [], []
    for lab in chosen:
        counts = free[free.label == lab].model_mode.astype(int).value_counts()
        if counts.empty:
            continue
        top = counts.max()
        mm = max(int(k) for k, n in counts.items() if n == top)  # max_by_key keeps the last
        if mm >= 1:
            labels.append(lab)
            model_mode.append(mm - 1)
    masses = pq.read_table(work / "ingest" / "masses.parquet").to_pandas().set_index("board_id")
    board_ids = [b for b in step1_boards(free, masses) if b not in held_out]
    params = list(cfg["params"])
    mass_updated = "mass_scale" in params
    units, freq, mass = [], [], []
    for b in board_ids:
        rows = free[(free.board_id == b) & free.label.isin(labels)]
        m_obs = None
        if b in masses.index and mass_updated:
            r = masses.loc[b]
            if r.n_stable >= 1 and np.isfinite(r.mass_g):
                res2 = r.resolution_g**2 / 12.0
                sd2 = r.std_g**2 + res2 if r.inconsistent else r.std_g**2 / r.n_stable + res2
                m_obs = (float(r.mass_g), max(math.sqrt(sd2), 2e-4 * abs(r.mass_g), 1e-9))
        if rows.empty and m_obs is None:
            continue
        u = len(units)
        units.append(b)
        for _, p in rows.iterrows():
            w = 2.0 * math.pi * p.freq_hz
            freq.append((u, labels.index(p.label), w * w, p.measurement_id))
        if m_obs is not None:
            mass.append((u, m_obs[0], m_obs[1]))
    return {
        "labels": labels,
        "model_mode": model_mode,
        "units": units,
        "params": params,
        "freq_unit": np.array([f[0] for f in freq], int),
        "freq_mode": np.array([f[1] for f in freq], int),
        "lam_hat": np.array([f[2] for f in freq]),
        "freq_meas": [f[3] for f in freq],
        "mass_unit": np.array([m[0] for m in mass], int),
        "mass_g": np.array([m[1] for m in mass]),
        "mass_sd": np.array([m[2] for m in mass]),
        "nominal_mass_g": nominal_mass_g,
        "mass_idx": params.index("mass_scale") if mass_updated else None,
        # ε fixed for every mode (hbmu --eps-fixed), or None: inferred per mode.
        "eps_fixed": cfg["eps"]["value"] if cfg["eps"]["kind"] == "fixed" else None,
    }


def log_lik_numpy(data, lam, ok, eps, x):
    """modal::log_lik summed over the units (lam (B, L), eps (L,), x (B, d))."""
    if not ok.all():
        return -np.inf
    u, m, lh = data["freq_unit"], data["freq_mode"], data["lam_hat"]
    sd = eps[m] * lh
    z = (lh - lam[u, m]) / sd
    ll = -np.sum(0.5 * (LN_2PI + z * z) + np.log(eps[m]) + np.log(lh))
    if data["mass_idx"] is not None and len(data["mass_unit"]):
        mod = data["nominal_mass_g"] * (1.0 + x[data["mass_unit"], data["mass_idx"]])
        zm = (data["mass_g"] - mod) / data["mass_sd"]
        ll -= np.sum(0.5 * (LN_2PI + zm * zm) + np.log(data["mass_sd"]))
    return ll


# ---------------------------------------------------------------------------------------------
# hbmu's outputs.


def hbmu_draws(hbmu_out):
    pop = pq.read_table(hbmu_out / "population.parquet").to_pandas()
    boards = pq.read_table(hbmu_out / "boards.parquet").to_pandas()
    return pop, boards


def nominal_mass_from(boards):
    r = boards.mass_g / boards.mass_scale
    if not np.allclose(r, r.iloc[0], rtol=1e-12, atol=0):
        raise SystemExit("boards.parquet: mass_g / mass_scale is not constant; cannot recover m_nom")
    return float(r.iloc[0])


def board_x(boards, data, pred):
    """hbmu's draws as x (n_draws, B, d), keyed by (run, draw)."""
    cols = data["params"]
    boards = boards.sort_values(["run", "draw", "board_id"])
    keys = boards[["run", "draw"]].drop_duplicates().to_numpy()
    nb = len(data["units"])
    arr = boards[cols].to_numpy().reshape(len(keys), nb, len(cols))
    ids = boards.board_id.to_numpy().reshape(len(keys), nb)
    assert (ids == np.array(data["units"])[None, :]).all(), "board order"
    return keys, arr / pred.reference[None, None, :] - 1.0


def check_forward(hbmu_out, data, pred, keys, x):
    """Posterior-predictive frequency mean/sd of the updated modes at the draws hbmu's
    `residuals` uses, against residuals.parquet."""
    res = pq.read_table(hbmu_out / "residuals.parquet").to_pandas()
    res = res[res.used_for_updating]
    rep = json.loads((hbmu_out / "update_report.json").read_text())
    particles = int(rep["particles"])
    step = max(particles // int(load_config(hbmu_out).get("residual_draws", 250)), 1)
    sel = keys[:, 1] % step == 0
    xs = x[sel]
    nb = xs.shape[1]
    lam, ok = pred.predict(xs.reshape(-1, xs.shape[2]))
    f = np.sqrt(np.maximum(lam, 0)) / (2 * math.pi)
    f = f.reshape(xs.shape[0], nb, -1)
    okb = ok.reshape(xs.shape[0], nb)
    worst_mean = worst_sd = 0.0
    n = 0
    for _, r in res.iterrows():
        b = data["units"].index(r.board_id)
        m = data["labels"].index(r.label)
        v = f[okb[:, b], b, m]
        worst_mean = max(worst_mean, abs(v.mean() / r.model_freq_hz_mean - 1.0))
        worst_sd = max(worst_sd, abs(v.std() / r.model_freq_hz_sd - 1.0))
        n += 1
    return {
        "rows": n,
        "draws_used": int(xs.shape[0]),
        "tracked_share": float(okb.mean()),
        "max_rel_err_predictive_mean": worst_mean,
        "max_rel_err_predictive_sd": worst_sd,
    }


# ---------------------------------------------------------------------------------------------
# The PyMC model.


def build_model(data, pred, cfg):
    import pymc as pm
    import pytensor.tensor as pt
    from pytensor.graph.basic import Apply
    from pytensor.graph.op import Op

    class ModalOp(Op):
        """x (B, d) relative deviations -> (λ (B, L) in label order, tracked (B,) as 0/1)."""

        __props__ = ()

        def make_node(self, x):
            x = pt.as_tensor_variable(x)
            return Apply(self, [x], [pt.dmatrix(), pt.dvector()])

        def perform(self, node, inputs, outputs):
            lam, ok = pred.predict(inputs[0])
            outputs[0][0] = lam
            outputs[1][0] = ok.astype(np.float64)

    eps_prior = cfg["eps"]
    if cfg.get("delta") is not None:
        raise SystemExit("hbmu ran with mode-shape terms; the peer needs --no-shapes (see the docstring)")
    nb, d, nl = len(data["units"]), len(data["params"]), len(data["labels"])
    coords = {"board": data["units"], "param": data["params"], "label": data["labels"]}
    with pm.Model(coords=coords) as model:
        mu = pm.Normal("mu", 0.0, cfg["prior_width"], dims="param")
        chol, _, _ = pm.LKJCholeskyCov(
            "chol",
            n=d,
            eta=cfg["lkj_eta"],
            sd_dist=pm.HalfNormal.dist(cfg["sigma_scale"], shape=d),
            compute_corr=True,
        )
        if data["eps_fixed"] is None:
            eps = pm.LogNormal("eps", math.log(eps_prior["median"]), eps_prior["log_sd"], dims="label")
        else:
            eps = fixed_eps(data)
        z = pm.Normal("z", 0.0, 1.0, dims=("board", "param"))
        x = pm.Deterministic("x", mu[None, :] + z @ chol.T, dims=("board", "param"))
        lam, ok = ModalOp()(x)
        u, m, lh = data["freq_unit"], data["freq_mode"], data["lam_hat"]
        pm.Normal("lam_obs", mu=lam[u, m], sigma=eps[m] * lh, observed=lh)
        if data["mass_idx"] is not None and len(data["mass_unit"]):
            pm.Normal(
                "mass_obs",
                mu=data["nominal_mass_g"] * (1.0 + x[data["mass_unit"], data["mass_idx"]]),
                sigma=data["mass_sd"],
                observed=data["mass_g"],
            )
        pm.Potential("tracked", pt.switch(pt.all(ok > 0.5), 0.0, -np.inf))
    assert nl == len(data["labels"]) and nb == len(data["units"])
    return model


class PointMaker:
    """Value-variable points of the PyMC model from natural values (mu, chol packed, eps, z):
    each free variable's forward transform compiled once."""

    def __init__(self, model):
        import pytensor
        import pytensor.tensor as pt

        self.model = model
        self.fns = {}
        for v in model.free_RVs:
            tr = model.rvs_to_transforms.get(v)
            if tr is None:
                continue
            inp = pt.tensor(dtype="float64", shape=(None,) * v.ndim)
            out = tr.forward(inp, *v.owner.inputs)
            self.fns[v.name] = pytensor.function([inp], out, on_unused_input="ignore")

    def __call__(self, natural):
        point = {}
        for v in self.model.free_RVs:
            val = np.asarray(natural[v.name], float)
            if v.name in self.fns:
                val = self.fns[v.name](val)
            point[self.model.rvs_to_values[v].name] = np.asarray(val, float)
        return point

    def from_hbmu(self, mu, sigma, corr, eps, x):
        """From hbmu-style values: μ, σ (relative), Ω, ε and the boards' x."""
        d = len(mu)
        lchol = np.linalg.cholesky(np.outer(sigma, sigma) * corr)
        z = np.linalg.solve(lchol, (x - mu[None, :]).T).T
        # LKJCholeskyCov packs the lower triangle row by row.
        return self({"mu": mu, "chol": lchol[np.tril_indices(d)], "eps": eps, "z": z})


def hbmu_natural(row, data, pred):
    """μ, σ (relative), Ω and ε of one population.parquet row."""
    p = data["params"]
    d = len(p)
    ref = pred.reference
    mu = np.array([row[f"mu_{q}"] for q in p]) / ref - 1.0
    sigma = np.array([row[f"sigma_{q}"] for q in p]) / ref
    corr = np.eye(d)
    for a in range(d):
        for b in range(a + 1, d):
            corr[a, b] = corr[b, a] = row[f"corr_{p[a]}_{p[b]}"]
    if data["eps_fixed"] is None:
        eps = np.array([row[f"eps_{lab}"] for lab in data["labels"]])
    else:
        eps = fixed_eps(data)
    return mu, sigma, corr, eps


def fixed_eps(data):
    """ε of every label when it is fixed (hbmu --eps-fixed)."""
    return np.full(len(data["labels"]), float(data["eps_fixed"]))


def check_likelihood(model, maker, data, pred, pop, keys, x, n_check=8):
    """The PyMC model's log-likelihood at hbmu draws against modal::log_lik in NumPy."""
    f = model.compile_fn(model.datalogp, inputs=model.value_vars, on_unused_input="ignore")
    pop = pop.sort_values(["run", "draw"]).reset_index(drop=True)
    rng = np.random.default_rng(1)
    idx = rng.choice(len(keys), size=min(n_check, len(keys)), replace=False)
    rows = []
    for i in idx:
        row = pop[(pop.run == keys[i, 0]) & (pop.draw == keys[i, 1])].iloc[0]
        mu, sigma, corr, eps = hbmu_natural(row, data, pred)
        point = maker.from_hbmu(mu, sigma, corr, eps, x[i])
        ll_pymc = float(f(point))
        lam, ok = pred.predict(x[i])
        ll_np = float(log_lik_numpy(data, lam, ok, eps, x[i]))
        rows.append((int(keys[i, 0]), int(keys[i, 1]), ll_pymc, ll_np))
    diffs = [abs(a - b) for _, _, a, b in rows]
    return {
        "draws": [{"run": r, "draw": dr, "loglik_pymc": a, "loglik_numpy": b} for r, dr, a, b in rows],
        "max_abs_diff": max(diffs),
    }


def check_mass(model, maker, data, pred, pop, keys, x, idata, n=400):
    """Where the posterior mass is, judged by the PyMC model itself: its log posterior density
    (prior with the Jacobians of its unconstrained value variables + log-likelihood) and its
    log-likelihood at hbmu's draws and at PyMC's final particles (n of each, evenly spaced)."""
    f_lp = model.compile_fn(model.logp(), inputs=model.value_vars, on_unused_input="ignore")
    f_ll = model.compile_fn(model.datalogp, inputs=model.value_vars, on_unused_input="ignore")
    pop = pop.sort_values(["run", "draw"]).set_index(["run", "draw"])
    out = {}
    pts = []
    for i in np.linspace(0, len(keys) - 1, min(n, len(keys))).astype(int):
        row = pop.loc[(keys[i, 0], keys[i, 1])]
        pts.append(maker.from_hbmu(*hbmu_natural(row, data, pred), x[i]))
    out["hbmu_draws"] = pts
    post = idata.posterior
    c, m = post.sizes["chain"], post.sizes["draw"]
    pts = []
    for k in np.linspace(0, c * m - 1, min(n, c * m)).astype(int):
        ci, di = divmod(int(k), m)
        nat = {v: post[v].values[ci, di] for v in ("mu", "chol", "eps", "z") if v in post}
        pts.append(maker(nat))
    out["pymc_particles"] = pts
    res = {}
    for name, ps in out.items():
        lp = np.array([float(f_lp(p)) for p in ps])
        ll = np.array([float(f_ll(p)) for p in ps])
        res[name] = {"points": len(ps), "logp_mean": float(lp.mean()), "logp_max": float(lp.max()),
                     "loglik_mean": float(ll.mean()), "loglik_max": float(ll.max())}
    return res


# ---------------------------------------------------------------------------------------------
# Diagnostics.


def hyper_names(data):
    p, labs = data["params"], data["labels"]
    names = [f"mu_{q}" for q in p] + [f"sigma_{q}" for q in p]
    names += [f"corr_{p[a]}_{p[b]}" for a in range(len(p)) for b in range(a + 1, len(p))]
    if data["eps_fixed"] is None:
        names += [f"eps_{lab}" for lab in labs]
    return names


def hbmu_arrays(pop, boards, data):
    """{name: (chains, draws)} of the hyperparameters and board parameters of hbmu."""
    pop = pop.sort_values(["run", "draw"])
    runs = sorted(pop.run.unique())
    out = {}
    for n in hyper_names(data):
        out[n] = np.stack([pop[pop.run == r][n].to_numpy() for r in runs])
    boards = boards.sort_values(["run", "draw", "board_id"])
    for b in data["units"]:
        sub = boards[boards.board_id == b]
        for q in data["params"]:
            out[f"{q}[{b}]"] = np.stack([sub[sub.run == r][q].to_numpy() for r in runs])
    return out


def pymc_arrays(idata, data, pred):
    post = idata.posterior
    p = data["params"]
    ref = pred.reference
    mu = post["mu"].values  # (c, n, d)
    chol_corr = post["chol_corr"].values
    stds = post["chol_stds"].values
    x = post["x"].values  # (c, n, B, d)
    out = {}
    for k, q in enumerate(p):
        out[f"mu_{q}"] = ref[k] * (1.0 + mu[..., k])
    for k, q in enumerate(p):
        out[f"sigma_{q}"] = ref[k] * stds[..., k]
    for a in range(len(p)):
        for b in range(a + 1, len(p)):
            out[f"corr_{p[a]}_{p[b]}"] = chol_corr[..., a, b]
    if data["eps_fixed"] is None:
        for k, lab in enumerate(data["labels"]):
            out[f"eps_{lab}"] = post["eps"].values[..., k]
    for j, b in enumerate(data["units"]):
        for k, q in enumerate(p):
            out[f"{q}[{b}]"] = ref[k] * (1.0 + x[..., j, k])
    return out


def _f(v):
    return float(np.asarray(v, float).ravel()[0])


def diagnose(arrs):
    import arviz as az

    rows = {}
    for n, a in arrs.items():
        a = np.asarray(a, float)
        rows[n] = {
            "mean": float(a.mean()),
            "sd": float(a.std()),
            "r_hat": _f(az.rhat(a)),
            "ess_bulk": _f(az.ess(a, method="bulk")),
            "ess_tail": _f(az.ess(a, method="tail")),
            "mcse_mean": _f(az.mcse(a, method="mean")),
            # Distinct values per chain (mean over chains): a collapsed SMC run has few.
            "distinct_per_chain": float(np.mean([len(np.unique(c)) for c in a])),
        }
    return rows


def slowest(diag, names):
    """The name and bulk ESS of the parameter with the lowest bulk ESS."""
    ok = [n for n in names if np.isfinite(diag[n]["ess_bulk"])]
    n = min(ok, key=lambda k: diag[k]["ess_bulk"]) if ok else names[0]
    return n, diag[n]["ess_bulk"]


# ---------------------------------------------------------------------------------------------
# Runs.


def run_hbmu(hbmu, work, out, draws, chains, cores, rom_basis, seed, hold_out=(), eps_fixed=None):
    cmd = [
        "/usr/bin/time", "-f", "TIME %e %U %S %M",
        hbmu, "--threads", str(cores), "update", "boards",
        str(work / "ingest"), str(work / "pair"), "--extract", str(work / "extract"),
        "--particles", str(draws), "--runs", str(chains), "--rom-basis", str(rom_basis),
        "--no-shapes", "--board-coordinates", "natural",
        # The PyMC model below writes σ ~ HalfNormal and no model-error term: hbmu's
        # defaults are a log-normal σ prior and a per-board model-error term.
        "--sigma-prior", "half-normal", "--no-model-error",
        "--seed", str(seed), "--out", str(out), "--force",
    ] + (["--hold-out", ",".join(hold_out)] if hold_out else []) + (
        ["--eps-fixed", repr(eps_fixed)] if eps_fixed is not None else [])
    print("$ " + " ".join(cmd), flush=True)
    load = os.getloadavg()
    p = subprocess.run(cmd, capture_output=True, text=True)
    m = re.search(r"TIME ([\d.]+) ([\d.]+) ([\d.]+) (\d+)", p.stderr)
    tail = "\n".join((p.stdout + p.stderr).strip().splitlines()[-6:])
    if p.returncode not in (0, 3) or not m:
        raise SystemExit(f"hbmu failed (exit {p.returncode}):\n{p.stdout}\n{p.stderr}")
    print(tail, flush=True)
    # The CLI's summary line: "… N ROM evaluations in S s" (the sampler's own time).
    ms = re.search(r"(\d+) ROM evaluations in ([\d.]+) s", p.stdout + p.stderr)
    return {
        "rom_evaluations": int(ms.group(1)) if ms else None,
        "sampler_s_reported": float(ms.group(2)) if ms else None,
        "command": " ".join(cmd[3:]),
        "exit_code": p.returncode,
        "wall_s": float(m.group(1)),
        "user_s": float(m.group(2)),
        "system_s": float(m.group(3)),
        "max_rss_kb": int(m.group(4)),
        "load_average_before": load,
        "load_average_after": os.getloadavg(),
    }


def run_pymc(model, draws, chains, cores, seed, threshold, corr_threshold, progressbar, kernel):
    import pymc as pm
    from pymc.smc import kernels

    load = os.getloadavg()
    print(f"(load average before: {load[0]:.2f})", flush=True)
    t0 = time.perf_counter()
    with model:
        idata = pm.sample_smc(
            draws=draws,
            chains=chains,
            cores=cores,
            blas_cores=cores,
            random_seed=seed,
            kernel=getattr(kernels, kernel),
            threshold=threshold,
            correlation_threshold=corr_threshold,
            progressbar=progressbar,
            compute_convergence_checks=False,
        )
    wall = time.perf_counter() - t0
    return idata, wall


def _flat(v):
    """A ragged (object) or regular array of numbers -> a flat float array."""
    if isinstance(v, (list, tuple, np.ndarray)):
        return np.concatenate([_flat(e) for e in v]) if len(v) else np.zeros(0)
    return np.array([np.nan if v is None else float(v)])


def pymc_stats(idata, chains):
    """Per chain: the stages' β, acceptance and the final log marginal likelihood. (PyMC
    5.28 keeps every stage's values when the chains run in parallel, only the last ones
    otherwise; with chains of unequal stage counts the per-chain lists arrive as one ragged
    object array of shape (1, chains).)"""
    ss = idata.sample_stats
    out = {}
    for k in ("log_marginal_likelihood", "beta", "accept_rate", "mean_accept_rate"):
        if k in ss:
            v = np.asarray(ss[k].values, dtype=object)
            if v.shape[0] != chains:
                v = v.reshape(-1)
            if len(v) != chains:
                raise SystemExit(f"sample_stats.{k}: unexpected shape {ss[k].values.shape}")
            out[k] = [_flat(v[c]) for c in range(chains)]
    lml = [float(a[np.isfinite(a)][-1]) if np.isfinite(a).any() else float("nan")
           for a in out.get("log_marginal_likelihood", [])]
    betas = [[float(v) for v in a] for a in out.get("beta", [])]
    acc = [[float(v) for v in a] for a in out.get("accept_rate", out.get("mean_accept_rate", []))]
    return {"log_marginal_likelihood": lml, "stages": [len(b) for b in betas],
            "beta_per_stage": betas, "accept_rate_per_stage": acc}


def fmt(v, w=10):
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return f"{'—':>{w}}"
    if isinstance(v, float):
        return f"{v:>{w}.4g}"
    return f"{v!s:>{w}}"


def main():
    warnings.filterwarnings("ignore", message="PyTensor could not link to a BLAS")
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("work", type=Path, help="demo work directory (ingest/, pair/, extract/)")
    ap.add_argument("out_json", type=Path)
    g = ap.add_mutually_exclusive_group(required=True)
    g.add_argument("--hbmu", help="hbmu binary: run step 1 (timed) first")
    g.add_argument("--hbmu-out", type=Path, help="existing step-1 output directory (--no-shapes)")
    ap.add_argument("--hbmu-wall", type=float, help="wall seconds of the --hbmu-out run, if known")
    ap.add_argument("--draws", type=int, default=2000, help="particles per run/chain (both tools)")
    ap.add_argument("--chains", type=int, default=4, help="independent runs/chains (both tools)")
    ap.add_argument("--cores", type=int, default=2)
    ap.add_argument("--seed", type=int, default=20261122)
    ap.add_argument("--rom-basis", type=int, default=30)
    ap.add_argument("--threshold", type=float, default=0.5, help="PyMC SMC ESS threshold")
    ap.add_argument("--correlation-threshold", type=float, default=0.01,
                    help="PyMC IMH/MH: stop a stage's mutations when the correlation drops less")
    ap.add_argument("--kernel", choices=("IMH", "MH"), default="IMH",
                    help="PyMC SMC kernel (IMH is PyMC's default)")
    ap.add_argument("--pymc-draws", type=int, help="PyMC particles per chain (default --draws)")
    ap.add_argument("--skip-pymc", action="store_true", help="checks only, no PyMC sampling")
    ap.add_argument("--scratch", type=Path, help="where hbmu writes (default: a temporary dir)")
    ap.add_argument("--progressbar", action="store_true")
    ap.add_argument("--eps-fixed", type=float,
                    help="fix ε (relative eigenvalue error) of every mode in both tools (hbmu "
                         "--eps-fixed): a wider, lower-dimensional posterior")
    ap.add_argument("--boards", type=int,
                    help="update only the first N boards (sorted ids; hbmu --hold-out the rest): "
                         "a smaller posterior, to find one PyMC's SMC converges on")
    a = ap.parse_args()
    work = a.work.resolve()
    result = {"work": str(work), "draws": a.draws, "chains": a.chains, "cores": a.cores}

    # 1. hbmu.
    if a.hbmu:
        scratch = a.scratch or Path(tempfile.mkdtemp(prefix="hbmu-pymc-peer."))
        hbmu_out = scratch / "hbmu"
        hold_out = []
        if a.boards:
            masses = pq.read_table(work / "ingest" / "masses.parquet").to_pandas()
            hold_out = step1_boards(free_pairs(work), masses.set_index("board_id"))[a.boards:]
        result["hbmu_run"] = run_hbmu(a.hbmu, work, hbmu_out, a.draws, a.chains, a.cores,
                                      a.rom_basis, a.seed, hold_out, a.eps_fixed)
        hbmu_wall = result["hbmu_run"]["wall_s"]
    else:
        hbmu_out = a.hbmu_out.resolve()
        hbmu_wall = a.hbmu_wall
        result["hbmu_run"] = {"output": str(hbmu_out), "wall_s": hbmu_wall}
    result["hbmu_run"]["output"] = str(hbmu_out)
    cfg = load_config(hbmu_out)
    rep = json.loads((hbmu_out / "update_report.json").read_text())
    ev = json.loads((hbmu_out / "evidence.json").read_text())

    # 2. The model's pieces.
    rom = Rom(hbmu_out / "rom.npz")
    pop, boards = hbmu_draws(hbmu_out)
    m_nom = nominal_mass_from(boards)
    data = select_data(work, cfg, m_nom, rep.get("held_out_boards") or [])
    if data["labels"] != list(rep["labels"]):
        raise SystemExit(f"labels differ: peer {data['labels']} vs hbmu {rep['labels']}")
    pred = Predictor(rom, data["model_mode"], data["params"])
    result["model"] = {
        "labels": data["labels"],
        "model_modes_1based": [m + 1 for m in data["model_mode"]],
        "boards": data["units"],
        "params": data["params"],
        "eigenvalue_terms": int(len(data["lam_hat"])),
        "mass_terms": int(len(data["mass_g"])),
        "nominal_mass_g": m_nom,
        "rom_dim": rom.r,
        "rom_k_terms": int(len(rom.k_terms)),
        "rom_m_identity": bool(rom.m_identity),
        "n_track": pred.n_track,
        "priors": {k: cfg[k] for k in ("prior_width", "sigma_scale", "lkj_eta", "eps", "delta")},
        "shape_terms": "left out of both runs (rom.npz has no shape operator at the scan points)",
    }
    print(f"model: {len(data['units'])} boards × {len(data['params'])} parameters, "
          f"{len(data['labels'])} labels, {len(data['lam_hat'])} eigenvalue terms, "
          f"{len(data['mass_g'])} mass terms; ROM r = {rom.r}, {len(rom.k_terms)} K terms", flush=True)

    # 3. Checks.
    keys, x = board_x(boards, data, pred)
    t0 = time.perf_counter()
    fwd = check_forward(hbmu_out, data, pred, keys, x)
    print(f"check (a) forward model vs residuals.parquet: {fwd['rows']} rows over "
          f"{fwd['draws_used']} draws, max rel. error of the predictive mean "
          f"{fwd['max_rel_err_predictive_mean']:.2e}, of the sd {fwd['max_rel_err_predictive_sd']:.2e}",
          flush=True)
    model = build_model(data, pred, cfg)
    maker = PointMaker(model)
    lik = check_likelihood(model, maker, data, pred, pop, keys, x)
    print(f"check (b) PyMC log-likelihood vs modal::log_lik (NumPy) at {len(lik['draws'])} hbmu draws: "
          f"max |Δ| = {lik['max_abs_diff']:.2e} (values ≈ {lik['draws'][0]['loglik_pymc']:.3f})", flush=True)
    # Cost of one PyMC log-likelihood evaluation (one particle, every board).
    f = model.compile_fn(model.datalogp, inputs=model.value_vars, on_unused_input="ignore")
    pt0 = model.initial_point()
    n_t = 200
    t1 = time.perf_counter()
    for _ in range(n_t):
        f(pt0)
    per_eval = (time.perf_counter() - t1) / n_t
    result["checks"] = {"forward": fwd, "likelihood": lik, "check_seconds": time.perf_counter() - t0,
                        "pymc_loglik_eval_s": per_eval}
    print(f"PyMC log-likelihood evaluation: {1e6 * per_eval:.0f} µs per particle ({len(data['units'])} boards)",
          flush=True)

    # 4. PyMC.
    names = hyper_names(data)
    hb = diagnose(hbmu_arrays(pop, boards, data))
    result["hbmu"] = {
        "diagnostics": hb,
        "log_evidence_runs": ev["log_evidence_runs"],
        "log_evidence_mean": ev["log_evidence_mean"],
        "log_evidence_standard_error": ev["log_evidence_standard_error"],
        "stages_per_run": rep.get("stages_per_run"),
        "max_r_hat_reported": rep.get("max_r_hat"),
        "min_ess_reported": rep.get("min_ess"),
    }
    s_name, s_ess = slowest(hb, names)
    result["hbmu"]["slowest_hyper"] = {"name": s_name, "ess_bulk": s_ess,
                                       "ess_per_s": s_ess / hbmu_wall if hbmu_wall else None}
    result["hbmu"]["slowest_mu_sigma"] = dict(
        zip(("name", "ess_bulk"), slowest(hb, names[: 2 * len(data["params"])])))
    if a.skip_pymc:
        a.out_json.write_text(json.dumps(result, indent=1, default=float))
        print(f"(--skip-pymc) wrote {a.out_json}")
        return
    pdraws = a.pymc_draws or a.draws
    print(f"PyMC sample_smc: draws {pdraws}, chains {a.chains}, cores {a.cores} …", flush=True)
    idata, pwall = run_pymc(model, pdraws, a.chains, a.cores, a.seed, a.threshold,
                            a.correlation_threshold, a.progressbar, a.kernel)
    stats = pymc_stats(idata, a.chains)
    try:
        idata.posterior.to_netcdf(str(a.out_json.with_suffix(".pymc_posterior.nc")))
    except Exception as e:  # noqa: BLE001 (the JSON is what matters)
        print(f"(could not save the PyMC posterior: {e})")
    py = diagnose(pymc_arrays(idata, data, pred))
    mass = check_mass(model, maker, data, pred, pop, keys, x, idata)
    p_name, p_ess = slowest(py, names)
    lml = np.array(stats["log_marginal_likelihood"])
    result["pymc"] = {
        "draws": pdraws,
        "kernel": a.kernel,
        "threshold": a.threshold,
        "correlation_threshold": a.correlation_threshold,
        "sample_smc_wall_s": pwall,
        "check_posterior_mass": mass,
        "diagnostics": py,
        "log_marginal_likelihood_chains": lml.tolist(),
        "log_marginal_likelihood_mean": float(np.mean(lml)),
        "log_marginal_likelihood_sd": float(np.std(lml, ddof=1)) if len(lml) > 1 else None,
        "stages": stats["stages"],
        "beta_per_stage": stats["beta_per_stage"],
        "accept_rate_per_stage": stats["accept_rate_per_stage"],
        "slowest_mu_sigma": dict(zip(("name", "ess_bulk"), slowest(py, names[: 2 * len(data["params"])]))),
        "load_average_after": os.getloadavg(),
        "slowest_hyper": {"name": p_name, "ess_bulk": p_ess, "ess_per_s": p_ess / pwall},
    }

    # 5. Agreement where both converge.
    comp = {}
    for n in hb:
        h, p = hb[n], py[n]
        conv = h["r_hat"] < RHAT_OK and p["r_hat"] < RHAT_OK
        se = math.hypot(h["mcse_mean"], p["mcse_mean"])
        comp[n] = {
            "converged_both": bool(conv),
            "z": (p["mean"] - h["mean"]) / se if se > 0 else None,
            "sd_ratio_pymc_over_hbmu": p["sd"] / h["sd"] if h["sd"] > 0 else None,
        }
    result["agreement"] = comp
    conv_z = [abs(c["z"]) for c in comp.values() if c["converged_both"] and c["z"] is not None]
    result["agreement_summary"] = {
        "compared": len(conv_z),
        "of": len(comp),
        "max_abs_z": max(conv_z) if conv_z else None,
        "share_abs_z_below_3": float(np.mean(np.array(conv_z) < 3)) if conv_z else None,
    }
    ratio = None
    if hbmu_wall and p_ess > 0:
        ratio = (s_ess / hbmu_wall) / (p_ess / pwall)
    result["ess_per_s_ratio_hbmu_over_pymc"] = ratio
    a.out_json.write_text(json.dumps(result, indent=1, default=float))

    # 6. The table.
    print()
    print(f"{'':28}{'hbmu':>12}{'PyMC':>12}")
    print(f"{'wall s':28}{fmt(hbmu_wall, 12)}{fmt(pwall, 12)}")
    print(f"{'slowest hyperparameter':28}{'':>12}{'':>12}")
    print(f"{'  hbmu':28}{s_name}")
    print(f"{'  PyMC':28}{p_name}")
    print(f"{'  its bulk ESS':28}{fmt(s_ess, 12)}{fmt(p_ess, 12)}")
    print(f"{'  ESS/s':28}{fmt(s_ess / hbmu_wall if hbmu_wall else None, 12)}{fmt(p_ess / pwall, 12)}")
    print(f"{'max R-hat (hyper)':28}{fmt(max(hb[n]['r_hat'] for n in names), 12)}"
          f"{fmt(max(py[n]['r_hat'] for n in names), 12)}")
    print(f"{'log evidence, mean':28}{fmt(ev['log_evidence_mean'], 12)}{fmt(float(np.mean(lml)), 12)}")
    print(f"{'  sd across runs':28}{fmt(ev['log_evidence_sd_across_runs'], 12)}"
          f"{fmt(result['pymc']['log_marginal_likelihood_sd'], 12)}")
    print(f"ESS/s ratio hbmu / PyMC: {fmt(ratio, 0)} (target ≥ 100)")
    print()
    hm, pm_ = mass["hbmu_draws"], mass["pymc_particles"]
    print(f"check (c) the PyMC model's log posterior density at hbmu's draws: mean {hm['logp_mean']:.1f}, "
          f"max {hm['logp_max']:.1f}; at PyMC's particles: mean {pm_['logp_mean']:.1f}, max {pm_['logp_max']:.1f} "
          f"(log-likelihood {hm['loglik_mean']:.1f} vs {pm_['loglik_mean']:.1f})")
    print(f"PyMC ({a.kernel}): stages per chain {result['pymc']['stages']}, final β "
          f"{[round(b[-1], 4) for b in result['pymc']['beta_per_stage']]}, last-stage acceptance "
          f"{[round(r[-1], 3) for r in result['pymc']['accept_rate_per_stage']]}")
    print()
    print(f"{'hyperparameter':34}{'hbmu mean':>12}{'sd':>10}{'R-hat':>8}{'ESS':>8}"
          f"{'PyMC mean':>12}{'sd':>10}{'R-hat':>8}{'ESS':>8}{'uniq':>6}{'z':>8}")
    for n in names:
        h, p, c = hb[n], py[n], comp[n]
        z = f"{c['z']:8.2f}" if c["converged_both"] and c["z"] is not None else f"{'(n.c.)':>8}"
        print(f"{n:34.34}{h['mean']:12.5g}{h['sd']:10.3g}{h['r_hat']:8.3f}{h['ess_bulk']:8.0f}"
              f"{p['mean']:12.5g}{p['sd']:10.3g}{p['r_hat']:8.3f}{p['ess_bulk']:8.0f}"
              f"{p['distinct_per_chain']:6.0f}{z}")
    s = result["agreement_summary"]
    print(f"board and hyper parameters with R-hat < {RHAT_OK} in both: {s['compared']} of {s['of']}; "
          f"max |z| {fmt(s['max_abs_z'], 0)}")
    print(f"wrote {a.out_json}")


if __name__ == "__main__":
    sys.exit(main())
