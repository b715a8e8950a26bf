"""Which CPU a run timed its decoders on, exactly enough to tell two of them apart.

The gate compares speed only between runs of one CPU (results/gate_speed.py): another
model moves a decoder's speed over its reference by more than a 10% gate allows
(docs/ci-gate.md). The model name alone does not say which CPU it is: a VM may report
"AMD EPYC" for a Rome, a Milan and a Genoa part alike, and one name covers parts whose
caches, instruction sets (a hypervisor may hide AVX-512) and microcode differ. So a
manifest records the CPU's identity as the kernel reports it (/proc/cpuinfo, and the
cache sizes from sysfs as lscpu reads them): vendor, family, model, stepping,
microcode, cache sizes and flags, and two runs are timed on the same CPU only when all
of these agree. Older manifests name only the model (`environment.cpu`); against
those, the name is all that is compared.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

CPUINFO = Path("/proc/cpuinfo")
SYSFS_CACHES = Path("/sys/devices/system/cpu/cpu0/cache")
# Compared one by one, in this order, so the first difference is the one named.
FIELDS = ("vendor", "family", "model", "stepping", "microcode", "model_name", "caches", "flags")
_INTEGERS = {"cpu family": "family", "model": "model", "stepping": "stepping"}


def parse_cpuinfo(text: str) -> dict[str, Any]:
    """The identity fields of the first processor listed in a /proc/cpuinfo text
    (every processor of one machine reads alike); {} when the text names none."""
    first = text.strip().split("\n\n", 1)[0]
    raw: dict[str, str] = {}
    for line in first.splitlines():
        key, sep, value = line.partition(":")
        if sep:
            raw.setdefault(key.strip(), value.strip())
    out: dict[str, Any] = {}
    if "vendor_id" in raw:
        out["vendor"] = raw["vendor_id"]
    for key, name in _INTEGERS.items():
        if raw.get(key, "").isdigit():
            out[name] = int(raw[key])
    if "microcode" in raw:
        out["microcode"] = raw["microcode"].lower()
    if "model name" in raw:
        out["model_name"] = raw["model name"]
    if "cache size" in raw:
        out["caches"] = {"cpuinfo": raw["cache size"]}
    flags = raw.get("flags")
    if flags is not None:
        out["flags"] = sorted(set(flags.split()))
    return out


def sysfs_caches(root: Path = SYSFS_CACHES) -> dict[str, str]:
    """Cache sizes of one core as lscpu reads them (L1d, L1i, L2, L3: "32K"); {} where
    the kernel does not say."""
    caches: dict[str, str] = {}
    for index in sorted(root.glob("index*")):
        try:
            level = (index / "level").read_text().strip()
            kind = (index / "type").read_text().strip()
            size = (index / "size").read_text().strip()
        except OSError:
            continue
        suffix = {"Data": "d", "Instruction": "i"}.get(kind, "")
        caches[f"L{level}{suffix}"] = size
    return caches


def read_cpu_identity(cpuinfo: Path = CPUINFO, caches: Path = SYSFS_CACHES) -> dict[str, Any]:
    """This machine's CPU identity for a manifest; {} where /proc/cpuinfo is unreadable
    (another OS: the manifest's model name is then all there is to compare)."""
    try:
        identity = parse_cpuinfo(cpuinfo.read_text())
    except OSError:
        return {}
    measured = sysfs_caches(caches)
    if measured:
        identity["caches"] = measured
    return identity


def _flag_difference(a: list[str], b: list[str]) -> str:
    def some(names: set[str]) -> str:
        shown = sorted(names)[:6]
        return ", ".join(shown) + (f" (+{len(names) - 6} more)" if len(names) > 6 else "")

    only_a, only_b = set(a) - set(b), set(b) - set(a)
    parts = [f"only the baseline's has {some(only_a)}"] if only_a else []
    parts += [f"only the candidate's has {some(only_b)}"] if only_b else []
    return "flags differ: " + "; ".join(parts)


def cpu_difference(baseline: Mapping[str, Any], candidate: Mapping[str, Any]) -> str:
    """'' when two manifests' `environment` blocks name the same CPU, else the first
    difference in words. By identity when both recorded one; by model name otherwise
    (an older manifest), and not at all when either names nothing."""
    a, b = baseline.get("cpu_identity") or {}, candidate.get("cpu_identity") or {}
    if not (a and b):
        names = baseline.get("cpu"), candidate.get("cpu")
        if None in names or names[0] == names[1]:
            return ""
        return f"model {names[0]!r} vs {names[1]!r}"
    for field in FIELDS:
        if field not in a or field not in b or a[field] == b[field]:
            continue  # what one side did not record cannot tell them apart
        if field == "flags":
            return _flag_difference(a[field], b[field])
        if field == "caches":
            differ = [k for k in sorted(set(a[field]) | set(b[field])) if a[field].get(k) != b[field].get(k)]
            return "cache sizes differ: " + ", ".join(
                f"{k} {a[field].get(k, '-')} vs {b[field].get(k, '-')}" for k in differ
            )
        return f"{field.replace('_', ' ')} {a[field]} vs {b[field]}"
    return ""


def describe_cpu(environment: Mapping[str, Any]) -> str:
    """A manifest's CPU in one phrase: the name, and family/model/stepping when recorded."""
    name = environment.get("cpu")
    identity = environment.get("cpu_identity") or {}
    parts = [f"{k} {identity[k]}" for k in ("family", "model", "stepping") if k in identity]
    if "microcode" in identity:
        parts.append(f"microcode {identity['microcode']}")
    count = environment.get("cpu_count")
    if count:
        parts.append(f"{count} CPUs")
    return f"{name} ({', '.join(parts)})" if parts else str(name)
