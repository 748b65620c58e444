"""Round-trip latency of pymodbus's synchronous TCP client reading the 6 input registers (function 04) of a
hydrolens simulator: the peer of benches/modbus.rs. Prints one line in the same format.

usage: modbus_latency.py HOST PORT [REQUESTS]
"""

import sys
import time

from pymodbus.client import ModbusTcpClient

WARM_UP = 500


def quantile(sorted_ns, q):
    rank = min(max(int(-(-q * len(sorted_ns) // 1)), 1), len(sorted_ns))
    return sorted_ns[rank - 1]


def main():
    host, port = sys.argv[1], int(sys.argv[2])
    requests = int(sys.argv[3]) if len(sys.argv) > 3 else 5000
    client = ModbusTcpClient(host, port=port, timeout=1, retries=0)
    if not client.connect():
        sys.exit(f"cannot connect to {host}:{port}")
    samples = []
    clock = time.perf_counter_ns
    for i in range(WARM_UP + requests):
        start = clock()
        reply = client.read_input_registers(0, count=6, device_id=1)
        elapsed = clock() - start
        if reply.isError() or len(reply.registers) != 6:
            sys.exit(f"request {i}: {reply}")
        if i >= WARM_UP:
            samples.append(elapsed)
    client.close()
    samples.sort()
    us = lambda ns: ns / 1e3  # noqa: E731
    mean = sum(samples) / len(samples)
    print(
        f"modbus_read6 python-pymodbus simulator=external requests={len(samples)} "
        f"p50_us={us(quantile(samples, 0.5)):.1f} p90_us={us(quantile(samples, 0.9)):.1f} "
        f"p99_us={us(quantile(samples, 0.99)):.1f} max_us={us(samples[-1]):.1f} mean_us={us(mean):.1f}"
    )


if __name__ == "__main__":
    main()
