"""Benchmark: von Mises–Fisher sampling on S^3, torchmocap vs scipy.stats.vonmises_fisher.

kappa = 1000 (the paper's value), mean (1, 0, 0, 0) and a generic mean, 200 / 3000 / 1e5 samples,
float64 for both (scipy samples in float64), plus our float32; one thread. Then what scipy cannot
do in one call: a different mean and concentration per sample (one call for 1e5 (mu, kappa)
pairs vs a Python loop of scipy calls), and the accuracy at large kappa (scipy's textbook envelope
parameter loses all precision near kappa ~ 1e8; see REFERENCE §2).

    OMP_NUM_THREADS=1 python experiments/benchmarks/vmf.py
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import scipy.stats as st
import torch

from torchmocap.distributions import VonMisesFisher, vmf_mean_resultant_length


def best_ms(fn, repeats: int) -> float:
    for _ in range(2):
        fn()
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best * 1e3


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=15)
    args = ap.parse_args()
    torch.set_num_threads(1)
    kappa = 1000.0
    g = torch.Generator().manual_seed(0)
    rng = np.random.default_rng(0)
    print("| mean | samples | scipy (ms) | ours float64 (ms) | ours float32 (ms) | "
          "speed-up f64 | speed-up f32 |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    mus = {"(1,0,0,0)": np.array([1.0, 0, 0, 0]),
           "generic": np.array([0.5, -0.5, 0.5, 0.5])}
    for label, mu in mus.items():
        sd = st.vonmises_fisher(mu, kappa)
        d64 = VonMisesFisher(torch.tensor(mu), torch.tensor(kappa, dtype=torch.float64))
        d32 = VonMisesFisher(torch.tensor(mu, dtype=torch.float32), torch.tensor(kappa))
        for n in (200, 3000, 100000):
            rep = args.repeats if n < 100000 else max(5, args.repeats // 3)
            t_sp = best_ms(lambda sd=sd, n=n: sd.rvs(n, random_state=rng), rep)
            t_64 = best_ms(lambda d=d64, n=n: d.sample((n,), generator=g), rep)
            t_32 = best_ms(lambda d=d32, n=n: d.sample((n,), generator=g), rep)
            print(f"| {label} | {n} | {t_sp:.3f} | {t_64:.3f} | {t_32:.3f} | "
                  f"{t_sp / t_64:.2f}x | {t_sp / t_32:.2f}x |", flush=True)

    # per-sample mean and concentration: one call vs a loop of scipy calls
    n = 100000
    mu = torch.nn.functional.normalize(torch.randn(n, 4, generator=g, dtype=torch.float64), dim=-1)
    kap = 10 ** (1 + 3 * torch.rand(n, generator=g, dtype=torch.float64))  # 10 .. 1e4
    t_ours = best_ms(lambda: VonMisesFisher(mu, kap).sample(generator=g), 5)
    m_sc = 2000
    mu_np, k_np = mu[:m_sc].numpy(), kap[:m_sc].numpy()

    def scipy_loop():
        return [st.vonmises_fisher(mu_np[i], k_np[i]).rvs(1, random_state=rng)
                for i in range(m_sc)]

    t_sc = best_ms(scipy_loop, 2) * n / m_sc
    x = VonMisesFisher(mu, kap).sample(generator=g)
    w = (x * mu).sum(-1)
    a = vmf_mean_resultant_length(kap, 4)
    z = float((w - a).mean() / (w - a).std() * np.sqrt(n))
    print()
    print(f"per-sample (mu, kappa), 1e5 pairs, kappa in [10, 1e4]: ours {t_ours:.1f} ms in one "
          f"call; scipy loop {t_sc:.0f} ms (timed on {m_sc} pairs, scaled): "
          f"{t_sc / t_ours:.0f}x; mean of mu.x - A4(kappa) = {float((w - a).mean()):.2e} "
          f"(z = {z:.2f})")

    # accuracy at large kappa: E[1 - mu.x] = 1 - A4(kappa) ~ 3 / (2 kappa)
    print()
    print("| kappa | E[1 - mu.x] exact | ours (float64) | ours (float32) | scipy |")
    print("|---:|---:|---:|---:|---:|")
    e1 = np.array([1.0, 0, 0, 0])
    for kk in (1e4, 1e6, 1e8):
        exact = 1 - float(vmf_mean_resultant_length(torch.tensor(kk, dtype=torch.float64), 4))
        vals = []
        for dt in (torch.float64, torch.float32):
            xs = VonMisesFisher(torch.tensor(e1, dtype=dt), torch.tensor(kk, dtype=dt)).sample(
                (200000,), generator=g).double()
            vals.append(float((0.5 * ((xs - torch.tensor(e1)) ** 2).sum(-1)).mean()))
        ys = st.vonmises_fisher(e1, kk).rvs(200000, random_state=rng)
        sc = float((0.5 * ((ys - e1) ** 2).sum(-1)).mean())
        print(f"| {kk:.0e} | {exact:.4e} | {vals[0]:.4e} | {vals[1]:.4e} | {sc:.4e} |")


if __name__ == "__main__":
    main()
