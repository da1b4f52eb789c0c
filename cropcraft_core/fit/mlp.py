"""The paper's MLP baseline: histogram statistics → parameters, learned from synthetic pairs.

Input: the observation's histograms (depth, lateral, Sobel) concatenated with the render height
and the mask area; output: the parameters scaled to [0, 1] over their box (sigmoid), then mapped
back. Training pairs come from the procedural model itself: parameters drawn uniformly, a canopy
built with its own seed, rendered from the row camera, its statistics computed exactly as a fit's
prediction is (supplementary "Baseline Implementation Details": soybean 10K pairs at render height
1.0 m and 10K at 1.25 m, maize 20K at 5 m; two hidden layers of 512; 200 epochs of Adam with
learning rate 1e-3 and weight decay 1e-5).

A trained network is cached on disk under ``$CROPCRAFT_CACHE`` (default ``~/.cache/cropcraft``)
keyed by crop and the hash of everything that shapes it (pairs, epochs, presets, layout, code
version), so it is trained once per configuration, not per run.
"""

from __future__ import annotations

import hashlib
import json
import os
import warnings
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from cropcraft_core import __version__
from cropcraft_core.config import CanopyLayout, default_layout
from cropcraft_core.config.params import bounds as param_bounds
from cropcraft_core.config.params import params_from_vector
from cropcraft_core.errors import ConfigError
from cropcraft_core.observe import HistogramStats, Observation, compute_stats, preset
from cropcraft_core.parallel import run_jobs

MODEL_VERSION = 1


@dataclass(frozen=True)
class MLPConfig:
    """Training settings (paper defaults)."""

    n_pairs: int = 20_000
    """Synthetic (statistics, parameters) pairs, split evenly over ``render_heights``."""
    render_heights: tuple[float, ...] | None = None
    """Render heights of the pairs; None: soybean (1.0, 1.25), maize (5.0)."""
    epochs: int = 200
    """Training epochs."""
    lr: float = 1e-3
    """Adam learning rate."""
    weight_decay: float = 1e-5
    """Adam weight decay."""
    hidden: int = 512
    """Width of each of the two hidden layers."""
    batch_size: int = 256
    """Minibatch size."""
    seed: int = 0
    """Seed of the parameter draws, canopy seeds and network initialisation."""

    def heights(self, crop: str) -> tuple[float, ...]:
        if self.render_heights:
            return tuple(self.render_heights)
        return (1.0, 1.25) if crop == "soybean" else (5.0,)


def features(stats: HistogramStats, render_height: float) -> np.ndarray:
    """(k,) float32 network input: depth, lateral and Sobel histograms, render height, mask
    area."""
    return np.concatenate(
        [stats.depth, stats.lateral, stats.sobel, [render_height, stats.mask_area]]
    ).astype(np.float32)


def network_preset(crop: str, render_height: float):
    """The histograms the network reads: the crop's preset at ``render_height`` with fixed bins
    (a ``depth_top_margin`` would fit every training pair's depth bins to the canopy that
    fixes the forward model's camera, and every observation's to its own)."""
    return preset(crop, render_height=render_height, depth_top_margin=None)


def observation_features(observation: Observation) -> np.ndarray:
    """The network's input for ``observation``: its statistics recomputed as the training
    pairs' are (:func:`training_pairs`): the crop's paper bins at the observation's render
    height, whatever bins the observation's own preset chose (e.g. ``depth_top_margin``), and
    the derivative histogram only where the crop's loss weighs it (maize's is all zeros in
    training, so an observation's, which it always computes for reports, would put the
    network far outside everything it saw)."""
    h = float(observation.preset.render_height)
    paper = network_preset(observation.crop, h)
    stats = compute_stats(observation.depth, observation.camera, observation.mask, paper)
    return features(stats, h)


#: Training pairs per job when :func:`training_pairs` is given an executor (each job builds its
#: own forward model, ~0.1 s, against ~45 ms a pair).
PAIRS_PER_JOB = 250


def _pairs_job(args) -> np.ndarray:
    """(n, k) features of one chunk of training pairs: (crop, layout, render height, unit
    parameter draws (n, d), canopy seeds (n,)). A module-level function, so that a process
    pool can run it."""
    from cropcraft_core.fit.forward import ForwardModel, observe_canopy
    from cropcraft_core.procedural import generate_canopy

    crop, layout, h, units, seeds = args
    b = param_bounds(crop)
    # any observation fixes the camera and preset of the forward model
    fm = ForwardModel(
        observe_canopy(generate_canopy(crop, None, layout, seed=0), network_preset(crop, h)),
        layout,
    )
    out = []
    for u, seed in zip(units, seeds, strict=True):
        params = params_from_vector(crop, b[:, 0] + u * (b[:, 1] - b[:, 0]))
        out.append(features(fm.stats(params, seed=int(seed)), h))
    return np.stack(out)


def training_pairs(
    crop: str,
    cfg: MLPConfig,
    layout: CanopyLayout | None = None,
    progress=None,
    executor=None,
) -> tuple[np.ndarray, np.ndarray]:
    """(n, k) features and (n, d) parameters scaled to [0, 1]. Every pair's parameters and
    canopy seed are drawn first (``cfg.seed``, in order), so the pairs are the same whether
    they are made here or spread over ``executor`` (anything with ``map``: a
    ``concurrent.futures`` process pool, a Dask client's executor) in jobs of
    :data:`PAIRS_PER_JOB`; ``progress(n)`` after each job with the pairs made so far."""
    rng = np.random.default_rng(cfg.seed)
    d = len(param_bounds(crop))
    layout = (layout or default_layout(crop)).with_(row_azimuth_deg=0.0)
    per = int(np.ceil(cfg.n_pairs / len(cfg.heights(crop))))
    jobs = []
    for h in cfg.heights(crop):
        units, seeds = np.empty((per, d)), np.empty(per, dtype=np.int64)
        for i in range(per):
            units[i] = rng.random(d)
            seeds[i] = rng.integers(2**31)
        for a in range(0, per, PAIRS_PER_JOB):
            z = slice(a, a + PAIRS_PER_JOB)
            jobs.append((crop, layout, h, units[z], seeds[z]))
    xs, made = [], 0
    for x in run_jobs(executor, _pairs_job, jobs):
        xs.append(x)
        made += len(x)
        if progress:
            progress(made)
    ys = np.concatenate([job[3] for job in jobs]).astype(np.float32)
    return np.concatenate(xs)[: cfg.n_pairs], ys[: cfg.n_pairs]


def _network(n_in: int, n_out: int, hidden: int):
    import torch

    return torch.nn.Sequential(
        torch.nn.Linear(n_in, hidden),
        torch.nn.ReLU(),
        torch.nn.Linear(hidden, hidden),
        torch.nn.ReLU(),
        torch.nn.Linear(hidden, n_out),
        torch.nn.Sigmoid(),
    )


def train(x: np.ndarray, y: np.ndarray, cfg: MLPConfig):
    """Train the network on features ``x`` (n, k) and scaled parameters ``y`` (n, d); returns
    (network, input mean, input std)."""
    import torch

    torch.manual_seed(cfg.seed)
    mu = x.mean(0)
    sd = x.std(0) + 1e-6
    xt = torch.from_numpy((x - mu) / sd)
    yt = torch.from_numpy(y)
    net = _network(x.shape[1], y.shape[1], cfg.hidden)
    opt = torch.optim.Adam(
        net.parameters(), lr=cfg.lr, betas=(0.9, 0.999), weight_decay=cfg.weight_decay
    )
    gen = torch.Generator().manual_seed(cfg.seed)
    for _ in range(cfg.epochs):
        perm = torch.randperm(len(xt), generator=gen)
        for i in range(0, len(xt), cfg.batch_size):
            idx = perm[i : i + cfg.batch_size]
            opt.zero_grad()
            loss = torch.nn.functional.mse_loss(net(xt[idx]), yt[idx])
            loss.backward()
            opt.step()
    net.eval()
    return net, mu, sd


#: Training spread (``x.std(0) + 1e-6``) at or below which an input counts as constant.
CONSTANT_SPREAD = 2e-6


def standardise(x: np.ndarray, mu: np.ndarray, sd: np.ndarray) -> np.ndarray:
    """Features ``x`` as the network was trained on them, ``(x - mu) / sd``, with 0 for the
    inputs that never varied in training (maize's render height, all pairs at 5 m; a histogram
    bin no pair reached): the network learnt nothing of them, and dividing a raised camera's
    5.1 m by the 1e-6 floor put every output on a bound of the box."""
    z = (np.asarray(x, dtype=np.float64) - mu) / sd
    return np.where(np.asarray(sd) <= CONSTANT_SPREAD, 0.0, z)


def cache_dir() -> Path:
    return Path(os.environ.get("CROPCRAFT_CACHE", Path.home() / ".cache" / "cropcraft")) / "mlp"


def config_hash(crop: str, cfg: MLPConfig, layout: CanopyLayout | None) -> str:
    lay = (layout or default_layout(crop)).with_(row_azimuth_deg=0.0)
    key = {
        "crop": crop,
        "cfg": asdict(cfg),
        "heights": cfg.heights(crop),
        "presets": [network_preset(crop, h).to_dict() for h in cfg.heights(crop)],
        "layout": lay.to_dict(),
        "version": __version__,
        "model": MODEL_VERSION,
    }
    return hashlib.sha256(json.dumps(key, sort_keys=True, default=str).encode()).hexdigest()[:16]


def load_or_train(
    crop: str, cfg: MLPConfig | None = None, layout: CanopyLayout | None = None, executor=None
):
    """The cached network for (crop, configuration), trained first if absent (its pairs made
    over ``executor`` where given: :func:`training_pairs`)."""
    import torch

    cfg = cfg or MLPConfig()
    if cfg.n_pairs < 2 or cfg.epochs < 1:
        raise ConfigError("MLP training needs at least 2 pairs and 1 epoch")
    path = cache_dir() / f"{crop}-{config_hash(crop, cfg, layout)}.pt"
    if path.exists():
        try:
            blob = torch.load(path, weights_only=False)
            net = _network(blob["n_in"], blob["n_out"], cfg.hidden)
            net.load_state_dict(blob["state"])
            net.eval()
            return net, blob["mu"], blob["sd"]
        except Exception as e:  # truncated, empty, another format: trained again over it
            warnings.warn(
                f"the cached MLP {path} cannot be read ({type(e).__name__}: {e}); training it "
                "again",
                stacklevel=2,
            )
    from cropcraft_core.export.atomic import atomic_path

    x, y = training_pairs(crop, cfg, layout, executor=executor)
    net, mu, sd = train(x, y, cfg)
    with atomic_path(path) as tmp:  # fsynced, and no partial file left on failure
        torch.save(
            {
                "state": net.state_dict(),
                "mu": mu,
                "sd": sd,
                "n_in": x.shape[1],
                "n_out": y.shape[1],
            },
            tmp,
        )
    return net, mu, sd


def predict_params(
    observation: Observation,
    cfg: MLPConfig | None = None,
    layout: CanopyLayout | None = None,
    executor=None,
) -> dict[str, float]:
    """The network's parameters for ``observation`` (trained first, over ``executor`` where
    given, if no cached network fits)."""
    import torch

    net, mu, sd = load_or_train(observation.crop, cfg, layout, executor)
    z = standardise(observation_features(observation), mu, sd)
    with torch.no_grad():
        u = net(torch.from_numpy(z[None].astype(np.float32))).numpy()[0]
    b = param_bounds(observation.crop)
    return params_from_vector(
        observation.crop, b[:, 0] + u.astype(np.float64) * (b[:, 1] - b[:, 0])
    )
