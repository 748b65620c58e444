"""padasip's RLS (FilterRLS, n=2, mu=0.99) on a recording: regressor [dP, omega] at row k, target omega at k+1.
The peer of `hydrolens estimate`. Times the CSV load and the filter separately (median of REPEATS runs) and prints
`padasip_rls rows=N load_s=… rls_s=… total_s=… rows_per_s=… rls_rows_per_s=… w=[…]`.

With OUT it also writes its estimates as `hydrolens estimate` does (a CSV with a header, a row per estimate: t_s,
the filter's output and its two weights, `numpy.savetxt` with `%.17g`, which reads back to the same doubles), the
same job end to end, and adds `save_s=… job_s=… job_rows_per_s=…` (load, filter and write; medians).

usage: padasip_rls.py REC.csv [REPEATS [OUT]]
"""

import os
import statistics
import sys
import time

import numpy as np
import padasip as pa


def load(path):
    with open(path) as f:
        header = f.readline().strip().split(",")
    data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    col = {name: i for i, name in enumerate(header)}
    dp = data[:, col["p_in_bar"]] - data[:, col["p_out_bar"]]
    omega = data[:, col["omega_rad_s"]]
    return data[:, col["t_s"]], dp, omega


def main():
    path = sys.argv[1]
    repeats = int(sys.argv[2]) if len(sys.argv) > 2 else 3
    out = sys.argv[3] if len(sys.argv) > 3 else None
    loads, fits, saves = [], [], []
    w = None
    for _ in range(repeats):
        t0 = time.perf_counter()
        t_s, dp, omega = load(path)
        t1 = time.perf_counter()
        x = np.column_stack([dp[:-1], omega[:-1]])
        d = omega[1:]
        f = pa.filters.FilterRLS(n=2, mu=0.99)
        y, _, weights = f.run(d, x)
        t2 = time.perf_counter()
        if out is not None:
            if os.path.exists(out):
                os.remove(out)  # a new file each time, as for ours (rewriting one in place makes ext4 flush it)
            estimates = np.column_stack([t_s[1:], y, weights])
            np.savetxt(out, estimates, fmt="%.17g", delimiter=",", header="t_s,omega_hat,w_dp,w_omega", comments="")
            saves.append(time.perf_counter() - t2)
        loads.append(t1 - t0)
        fits.append(t2 - t1)
        w = weights[-1]
    rows = len(d)
    load_s, rls_s = statistics.median(loads), statistics.median(fits)
    total = statistics.median(a + b for a, b in zip(loads, fits))
    print(
        f"padasip_rls rows={rows} load_s={load_s:.3f} rls_s={rls_s:.3f} total_s={total:.3f} "
        f"rows_per_s={rows / total:.0f} rls_rows_per_s={rows / rls_s:.0f} w=[{w[0]:.4f},{w[1]:.4f}]",
        end="",
    )
    if saves:
        job = statistics.median(a + b + c for a, b, c in zip(loads, fits, saves))
        print(f" save_s={statistics.median(saves):.3f} job_s={job:.3f} job_rows_per_s={rows / job:.0f}", end="")
    print()


if __name__ == "__main__":
    main()
