"""padasip's RLS (FilterRLS, n=2, mu=0.99) on a recording: regressor [dP, omega] at row k, target omega at k+1.
The peer of `hydrolens estimate`. Times the CSV load and the filter separately (median of REPEATS runs) and prints
`padasip_rls rows=N load_s=… rls_s=… total_s=… rows_per_s=… rls_rows_per_s=… w=[…]`.

usage: padasip_rls.py REC.csv [REPEATS]
"""

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
    return dp, omega


def main():
    path = sys.argv[1]
    repeats = int(sys.argv[2]) if len(sys.argv) > 2 else 3
    loads, fits = [], []
    w = None
    for _ in range(repeats):
        t0 = time.perf_counter()
        dp, omega = load(path)
        t1 = time.perf_counter()
        x = np.column_stack([dp[:-1], omega[:-1]])
        d = omega[1:]
        f = pa.filters.FilterRLS(n=2, mu=0.99)
        _, _, weights = f.run(d, x)
        t2 = time.perf_counter()
        loads.append(t1 - t0)
        fits.append(t2 - t1)
        w = weights[-1]
    rows = len(d)
    load_s, rls_s = statistics.median(loads), statistics.median(fits)
    total = statistics.median(a + b for a, b in zip(loads, fits))
    print(
        f"padasip_rls rows={rows} load_s={load_s:.3f} rls_s={rls_s:.3f} total_s={total:.3f} "
        f"rows_per_s={rows / total:.0f} rls_rows_per_s={rows / rls_s:.0f} w=[{w[0]:.4f},{w[1]:.4f}]"
    )


if __name__ == "__main__":
    main()
