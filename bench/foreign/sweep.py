"""bench/foreign/sweep.py BIN OUT N0 N1: a reviewer's random plants (seeded by their number): J ×0.2–5, B ×0.2–5,
four motor sizes, polls of 1–50 ms, 60–120 s, one of twelve load kinds, Coulomb and Stribeck friction, dead time,
leakage, torque offset and motor slip at random, and a nominal model exact, 20 % off, ×2 or ×0.5. Each is simulated,
estimated by rls-sgd and by the Kalman filter on the nominal model, and scored by score.py (one line a plant).
Kept as the reviewer wrote it but for the paths; about 1 s a plant."""
import random, subprocess, sys, os
here = os.path.dirname(os.path.abspath(__file__))
BIN, OUT = os.path.abspath(sys.argv[1]), sys.argv[2]
N0, N1 = int(sys.argv[3]), int(sys.argv[4])
os.makedirs(OUT, exist_ok=True)
os.chdir(OUT)
os.makedirs('sw', exist_ok=True)
def run(cmd, t=300):
    return subprocess.run(['timeout', str(t), 'nice'] + cmd, capture_output=True, text=True)
def score(name, rec, nom, J, B):
    for method in ('rls-sgd', 'kalman'):
        r = run([BIN, 'estimate', rec, '--model', nom, '--out', f'sw/{name}.{method}.csv', '--method', method])
        if r.returncode != 0:
            return f'ESTFAIL {method} rc={r.returncode} {r.stderr[:200]!r}'
    r = run(['python3', os.path.join(here, 'score.py'), rec, f'sw/{name}.rls-sgd.csv', f'sw/{name}.kalman.csv', f'{J}', f'{B}', name + '_', ''])
    for method in ('rls-sgd', 'kalman'):
        os.remove(f'sw/{name}.{method}.csv')
    return r.stdout.strip().replace(name + '_\t', '')
for i in range(N0, N1):
    R = random.Random(1000 + i)
    J = 0.08 * R.choice([0.2, 0.35, 0.5, 1, 1, 2, 3.5, 5]) * R.uniform(0.9, 1.1)
    B = 0.04 * R.choice([0.2, 0.5, 1, 1, 2, 5]) * R.uniform(0.9, 1.1)
    Dm = R.choice([32.0, 32.0, 20.0, 50.0, 80.0]); Dp = Dm * R.choice([0.5, 0.5, 0.3, 0.8])
    sm = R.choice([1.0, 1.0, 2.0, 5.0, 10.0, 20.0, 50.0])
    dur = R.choice([60, 60, 90, 120])
    sc = Dm / 32.0
    loads = [
        f'kind = "constant";torque_nm = {R.uniform(-5, 40)*sc:.3f}',
        f'kind = "steps";levels_nm = [{", ".join("%.2f" % (R.uniform(-15, 30)*sc) for _ in range(R.randint(2, 7)))}];period_s = {R.uniform(0.3, 8):.2f}',
        f'kind = "sine";mean_nm = {R.uniform(0, 15)*sc:.2f};amplitude_nm = {R.uniform(1, 15)*sc:.2f};period_s = {R.uniform(0.3, 12):.2f}',
        f'kind = "sines";mean_nm = {R.uniform(0, 15)*sc:.2f};amplitudes_nm = [{R.uniform(1,6)*sc:.2f}, {R.uniform(1,6)*sc:.2f}, {R.uniform(1,6)*sc:.2f}];periods_s = [{R.uniform(0.3,2):.2f}, {R.uniform(2,6):.2f}, {R.uniform(6,20):.2f}]',
        f'kind = "centrifugal";torque_nm = {R.uniform(3, 40)*sc:.2f};at_rad_s = 60.0',
        f'kind = "speed";constant_nm = {R.uniform(0, 8)*sc:.2f};linear_nm_s_rad = {R.choice([0.0, 0.0, R.uniform(0.005, 0.1)])*sc:.4f};quadratic_nm_s2_rad2 = {R.choice([0.0, R.uniform(0.0005, 0.005)])*sc:.5f}',
        f'kind = "random";mean_nm = {R.uniform(0, 15)*sc:.2f};sd_nm = {R.uniform(1, 8)*sc:.2f};correlation_s = {R.uniform(0.05, 5):.2f};seed = {R.randint(1, 999)}',
        f'kind = "impacts";base_nm = {R.uniform(0, 10)*sc:.2f};peak_nm = {R.uniform(5, 40)*sc:.2f};width_s = {R.uniform(0.01, 0.3):.3f};mean_interval_s = {R.uniform(0.3, 5):.2f};seed = {R.randint(1, 999)}',
        f'kind = "shaft_angle";mean_nm = {R.uniform(0, 15)*sc:.2f};amplitude_nm = {R.uniform(1, 10)*sc:.2f};cycles_per_rev = {R.choice([0.1, 0.25, 0.5, 1.0, 2.0])}',
        f'kind = "trend";start_nm = {R.uniform(0, 5)*sc:.2f};rate_nm_per_s = {R.uniform(0.05, 0.5)*sc:.3f};max_nm = {R.uniform(10, 40)*sc:.2f}',
        f'kind = "ramp";from_nm = {R.uniform(-5, 10)*sc:.2f};to_nm = {R.uniform(0, 30)*sc:.2f};start_s = {R.uniform(5, 20):.1f};duration_s = {R.uniform(5, 40):.1f}',
        'kind = "recorded"',
    ]
    load = R.choice(loads)
    effs = []
    if R.random() < 0.25: effs.append(f'[effects.coulomb_friction];torque_nm = {R.uniform(0.5, 4)*sc:.2f}')
    if R.random() < 0.1: effs.append(f'[effects.stribeck_friction];breakaway_nm = {R.uniform(4, 8)*sc:.2f};speed_rad_s = {R.uniform(0.5, 5):.2f}')
    if R.random() < 0.1: effs.append(f'[effects.dead_time];ms = {R.uniform(5, 60):.1f}')
    if R.random() < 0.1: effs.append(f'[effects.internal_leakage];l_min_per_bar = {R.uniform(0.005, 0.03):.3f}')
    if R.random() < 0.1: effs.append(f'[effects.torque_offset];torque_nm = {R.uniform(-3, 3)*sc:.2f}')
    if R.random() < 0.1: effs.append(f'[effects.motor_slip];rpm_per_nm = {R.uniform(0.5, 3):.2f}')
    if any('stribeck' in e for e in effs) and not any('coulomb' in e for e in effs):
        effs.insert(0, f'[effects.coulomb_friction];torque_nm = {1.0*sc:.2f}')
    pl = [f'J={J:.5f}', f'B={B:.5f}', f'Dm={Dm}', f'Dp={Dp}', f'sample_ms={sm}', 'maxhz=80.0', 'load=' + load]
    if effs: pl.append('eff=' + ';'.join(effs))
    name = f'sw{i:03d}'
    subprocess.run(['python3', os.path.join(here, 'plant.py'), f'sw/{name}.plant.toml'] + pl)
    r = run([BIN, 'simulate', '--model', f'sw/{name}.plant.toml', '--duration', str(dur), '--seed', str(i), '--out', f'sw/{name}.csv'])
    if r.returncode != 0:
        print(f'{name} SIMFAIL rc={r.returncode} {r.stderr[:200]!r}', flush=True); continue
    fJ, fB = R.choice([(1, 1), (1, 1), (R.uniform(0.8, 1.2), R.uniform(0.8, 1.2)), (R.uniform(0.8, 1.2), R.uniform(0.8, 1.2)), (2, 2), (0.5, 0.5), (2, 0.5), (R.uniform(0.8, 1.2), 1)])
    subprocess.run(['python3', os.path.join(here, 'plant.py'), f'sw/{name}.nom.toml', f'J={J*fJ:.5f}', f'B={B*fB:.5f}', f'Dm={Dm}', f'Dp={Dp}', f'sample_ms={sm}'])
    lab = f'{name}[J{J:.3f} B{B:.3f} Dm{Dm:g} {sm:g}ms {dur}s nom×{fJ:.2f}/{fB:.2f} load:{load.split(";")[0][6:].strip(chr(34))} eff:{",".join(e.split(";")[0][9:-1] for e in effs) or "-"}]'
    print(lab, score(name, f'sw/{name}.csv', f'sw/{name}.nom.toml', J, B), flush=True)
    os.remove(f'sw/{name}.csv')
