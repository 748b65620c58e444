"""The ablation table from bench/ablation/run.sh's outputs: per mechanism off, totals over the twelve seed sets.
Usage: python3 table.py OUT_DIR none MECHANISM..."""
import re
import sys

SETS = "tuned held-out fresh unseen final sealed novel last spare reserve blind untouched".split()


def totals(d):
    t = {}
    for s in SETS:
        for kind in ("six", "new"):
            text = open(f"{d}/{s}_{kind}.txt").read()
            row = [c.strip() for c in re.search(r"^\| all \|(.*)$", text, re.M).group(1).split("|")]
            near = re.match(r"(\d+)/(\d+)", row[2])
            sound = re.match(r"(\d+)/(\d+)", row[4])
            add = {
                "hold": int(re.search(r"^all: (\d+)/", text, re.M).group(1)),
                "no_harm": int(row[1]),
                "near": int(near.group(1)) if near else 0,
                "near_of": int(near.group(2)) if near else 0,
                "covered": int(row[3].split("/")[0]),
                "j_unsound": int(sound.group(2)) - int(sound.group(1)) if sound else 0,
                "fell_back": sum(int(x) for x in row[6].split("/")),
            }
            if kind == "six":
                gates = [int(m.group(2)) for m in re.finditer(r"^\| (\d+) ms \| (\d+)/24", text, re.M)
                         if m.group(1) in ("1", "5", "10")]
                add["gate"] = sum(gates)
                t.setdefault("six_gate_min", []).append(sum(gates))
            for k, v in add.items():
                t[f"{kind}_{k}"] = t.get(f"{kind}_{k}", 0) + v
    t["six_gate_min"] = min(t["six_gate_min"])
    return t


print("| off | six: hold (of 1152) | six: gate count, sum / lowest set (of 72) | six: no harm | new: no harm (of 1344) "
      "| new: hold | new: near the truth reference | coverage six / new | new: J unsound | J and B fell back six / new |")
print("|---|---|---|---|---|---|---|---|---|---|")
for m in sys.argv[2:]:
    t = totals(f"{sys.argv[1]}/{m}")
    print(f"| {'nothing' if m == 'none' else '`' + m + '`'} | {t['six_hold']} | {t['six_gate']} / {t['six_gate_min']} "
          f"| {t['six_no_harm']} | {t['new_no_harm']} | {t['new_hold']} | {t['new_near']} of {t['new_near_of']} "
          f"| {t['six_covered']} / {t['new_covered']} | {t['new_j_unsound']} | {t['six_fell_back']} / {t['new_fell_back']} |")
