"""bench/foreign/summary.py SWEEP.txt: the sweep's lines summed: rls-sgd's T̂_L RMSE over the Kalman filter's on the
nominal model (median, how many above 1.05, 1.2 and 1.5, how many at or below 0.95), and the checkpoints where J was
called identified with the truth outside 2 sd (`!`, J or B; the end is counted again where it falls on one)."""
import re, sys
ratios, breaches, jbad = [], 0, 0
for line in open(sys.argv[1]):
    m = re.search(r'ratio=([0-9.]+|nan)', line)
    if not m or m.group(1) == 'nan':
        continue
    ratios.append(float(m.group(1)))
    breaches += line.count('!')
    j = re.search(r'Jid>15%=(\d+)', line)
    jbad += j is not None and int(j.group(1)) > 0
ratios.sort()
n = len(ratios)
print(f'{n} plants: ratio median {ratios[n // 2]:.3f}; above 1.05: {sum(r > 1.05 for r in ratios)}, above 1.2: '
      f'{sum(r > 1.2 for r in ratios)}, above 1.5: {sum(r > 1.5 for r in ratios)}; at or below 0.95: '
      f'{sum(r <= 0.95 for r in ratios)}; checkpoints with J or B identified and the truth outside 2 sd: {breaches}; '
      f'plants with rows of J identified more than 15 % off: {jbad}')
