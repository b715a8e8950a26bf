"""CPU identity: parsed from /proc/cpuinfo texts of two EPYC generations and an Intel
part, compared field by field, and the gate timing only runs of one CPU (a generic
"AMD EPYC" name no longer hides a different generation); older manifests, which name
only the model, are still read and compared by name."""

from __future__ import annotations

import json

from results.cpu_identity import cpu_difference, describe_cpu, parse_cpuinfo, read_cpu_identity
from tests.test_gate import with_reference, write_run

ZEN_FLAGS = (
    "fpu vme de pse tsc msr pae mce cx8 apic sep mtrr pge mca cmov pat pse36 clflush mmx fxsr sse sse2 ht "
    "syscall nx mmxext fxsr_opt pdpe1gb rdtscp lm constant_tsc rep_good nopl nonstop_tsc cpuid extd_apicid "
    "tsc_known_freq pni pclmulqdq ssse3 fma cx16 sse4_1 sse4_2 x2apic movbe popcnt aes xsave avx f16c rdrand "
    "hypervisor lahf_lm cmp_legacy cr8_legacy abm sse4a misalignsse 3dnowprefetch osvw topoext ssbd ibrs ibpb "
    "stibp vmmcall fsgsbase tsc_adjust bmi1 avx2 smep bmi2 rdseed adx smap clflushopt clwb sha_ni xsaveopt "
    "xsavec xgetbv1 clzero xsaveerptr arat npt nrip_save umip rdpid"
)


def amd(name: str, family: int, model: int, stepping: int, microcode: str, extra_flags: str = "") -> str:
    """Two processors of a /proc/cpuinfo text as a KVM guest on an AMD host prints them."""
    block = f"""processor	: {{n}}
vendor_id	: AuthenticAMD
cpu family	: {family}
model		: {model}
model name	: {name}
stepping	: {stepping}
microcode	: {microcode}
cpu MHz		: 2449.998
cache size	: 512 KB
physical id	: 0
siblings	: 2
core id		: {{n}}
cpu cores	: 2
fpu		: yes
cpuid level	: 13
wp		: yes
flags		: {ZEN_FLAGS} {extra_flags}
bugs		: sysret_ss_attrs spectre_v1 spectre_v2 spec_store_bypass
bogomips	: 4899.99
TLB size	: 1024 4K pages
clflush size	: 64
cache_alignment	: 64
address sizes	: 48 bits physical, 48 bits virtual
power management:
"""
    return block.format(n=0) + "\n" + block.format(n=1) + "\n"


ROME = amd("AMD EPYC 7B12", 23, 49, 0, "0x1000065")
MILAN = amd("AMD EPYC 7B13", 25, 1, 1, "0xa0011d1", "pku ospke vaes vpclmulqdq rdpid fsrm")
# The same two generations behind a VM that names both "AMD EPYC".
ROME_GENERIC = ROME.replace("AMD EPYC 7B12", "AMD EPYC")
MILAN_GENERIC = MILAN.replace("AMD EPYC 7B13", "AMD EPYC")
ICE_LAKE = """processor	: 0
vendor_id	: GenuineIntel
cpu family	: 6
model		: 106
model name	: Intel(R) Xeon(R) Platinum 8375C CPU @ 2.90GHz
stepping	: 6
microcode	: 0xd000390
cpu MHz		: 2899.970
cache size	: 55296 KB
physical id	: 0
siblings	: 2
core id		: 0
cpu cores	: 1
fpu		: yes
cpuid level	: 27
wp		: yes
flags		: fpu vme de pse tsc msr pae mce cx8 apic sep mtrr pge mca cmov pat pse36 clflush mmx fxsr sse sse2 ss ht syscall nx pdpe1gb rdtscp lm constant_tsc rep_good nopl xtopology nonstop_tsc cpuid tsc_known_freq pni pclmulqdq ssse3 fma cx16 pcid sse4_1 sse4_2 x2apic movbe popcnt tsc_deadline_timer aes xsave avx f16c rdrand hypervisor lahf_lm abm 3dnowprefetch invpcid_single ssbd ibrs ibpb stibp ibrs_enhanced fsgsbase tsc_adjust bmi1 avx2 smep bmi2 erms invpcid avx512f avx512dq rdseed adx smap avx512ifma clflushopt clwb avx512cd sha_ni avx512bw avx512vl xsaveopt xsavec xgetbv1 xsaves wbnoinvd ida arat avx512vbmi pku ospke avx512_vbmi2 gfni vaes vpclmulqdq avx512_vnni avx512_bitalg tme avx512_vpopcntdq rdpid md_clear flush_l1d arch_capabilities
bugs		: spectre_v1 spectre_v2 spec_store_bypass swapgs mmio_stale_data eibrs_pbrsb gds bhi
bogomips	: 5799.94
clflush size	: 64
cache_alignment	: 64
address sizes	: 46 bits physical, 48 bits virtual
power management:

"""


def environment(cpuinfo: str, count: int = 2) -> dict:
    identity = parse_cpuinfo(cpuinfo)
    return {"cpu": identity["model_name"], "cpu_identity": identity, "cpu_count": count}


def test_each_part_is_parsed_into_its_identity():
    rome, milan, xeon = (parse_cpuinfo(t) for t in (ROME, MILAN, ICE_LAKE))
    assert (rome["vendor"], rome["family"], rome["model"], rome["stepping"]) == ("AuthenticAMD", 23, 49, 0)
    assert (milan["family"], milan["model"], milan["stepping"], milan["microcode"]) == (25, 1, 1, "0xa0011d1")
    assert (xeon["vendor"], xeon["family"], xeon["model"], xeon["stepping"]) == ("GenuineIntel", 6, 106, 6)
    assert xeon["microcode"] == "0xd000390" and xeon["caches"] == {"cpuinfo": "55296 KB"}
    assert xeon["model_name"] == "Intel(R) Xeon(R) Platinum 8375C CPU @ 2.90GHz"
    assert "avx512f" in xeon["flags"] and "avx512f" not in rome["flags"]
    assert rome["flags"] == sorted(set(ZEN_FLAGS.split()))  # a set, sorted: order never differs
    assert parse_cpuinfo("") == {}  # nothing listed: nothing to compare


def test_two_epyc_generations_under_one_generic_name_are_told_apart():
    rome, milan = environment(ROME_GENERIC), environment(MILAN_GENERIC)
    assert rome["cpu"] == milan["cpu"] == "AMD EPYC"
    assert cpu_difference(rome, milan) == "family 23 vs 25"
    assert cpu_difference(rome, environment(ROME_GENERIC, count=64)) == ""  # the count does not count
    assert cpu_difference(environment(ROME), environment(ICE_LAKE)) == "vendor AuthenticAMD vs GenuineIntel"
    assert describe_cpu(rome) == "AMD EPYC (family 23, model 49, stepping 0, microcode 0x1000065, 2 CPUs)"


def test_microcode_caches_and_flags_each_make_a_difference():
    base = environment(MILAN_GENERIC)
    updated = environment(MILAN_GENERIC.replace("0xa0011d1", "0xa0011d5"))
    assert cpu_difference(base, updated) == "microcode 0xa0011d1 vs 0xa0011d5"
    hidden = environment(MILAN_GENERIC.replace(" vaes vpclmulqdq", ""))  # a hypervisor masking them
    assert cpu_difference(base, hidden) == "flags differ: only the baseline's has vaes, vpclmulqdq"
    bigger = json.loads(json.dumps(base))
    bigger["cpu_identity"]["caches"] = {"L2": "1024K", "L3": "256M"}
    base["cpu_identity"]["caches"] = {"L2": "1024K", "L3": "32M"}
    assert cpu_difference(base, bigger) == "cache sizes differ: L3 32M vs 256M"


def test_an_older_manifest_with_only_the_name_is_compared_by_name():
    older = {"cpu": "AMD EPYC", "cpu_count": 2}
    assert cpu_difference(older, environment(MILAN_GENERIC)) == ""
    assert cpu_difference(older, environment(ICE_LAKE)) == (
        "model 'AMD EPYC' vs 'Intel(R) Xeon(R) Platinum 8375C CPU @ 2.90GHz'"
    )
    assert cpu_difference({}, environment(ICE_LAKE)) == ""  # a bare table names no CPU
    assert describe_cpu(older) == "AMD EPYC (2 CPUs)"


def test_this_machine_is_read_with_its_cache_sizes(tmp_path):
    (tmp_path / "cpuinfo").write_text(ICE_LAKE)
    for i, (level, kind, size) in enumerate(
        [(1, "Data", "48K"), (1, "Instruction", "32K"), (2, "Unified", "1280K")]
    ):
        index = tmp_path / "cache" / f"index{i}"
        index.mkdir(parents=True)
        for name, value in (("level", level), ("type", kind), ("size", size)):
            (index / name).write_text(f"{value}\n")
    identity = read_cpu_identity(tmp_path / "cpuinfo", tmp_path / "cache")
    assert identity["caches"] == {"L1d": "48K", "L1i": "32K", "L2": "1280K"}
    assert identity["model"] == 106
    assert read_cpu_identity(tmp_path / "missing", tmp_path / "cache") == {}


def test_a_run_manifest_records_the_identity():
    from harness.run.manifest import environment as recorded

    env = recorded()
    identity = env["cpu_identity"]
    assert env["cpu"]
    if identity:  # Linux: /proc/cpuinfo is there
        assert {"vendor", "family", "model", "flags"} <= set(identity)
        assert identity["model_name"] == env["cpu"]


def test_the_gate_times_only_runs_of_one_cpu(cli, tmp_path):
    df = with_reference(1400.0, 740.0)
    rome = write_run(tmp_path / "rome", df, calibration=4600.0, environment=environment(ROME_GENERIC))
    milan = write_run(tmp_path / "milan", df, calibration=4600.0, environment=environment(MILAN_GENERIC))
    again = write_run(tmp_path / "again", df, calibration=4600.0, environment=environment(ROME_GENERIC))
    older = write_run(tmp_path / "older", df, calibration=4600.0, cpu="AMD EPYC")
    code, out, err = cli("gate", "--baseline", str(rome), "--candidate", str(milan))
    text = " ".join(out.split())
    assert code == 0, out + err
    assert (
        "speed not comparable: the runs come from different CPUs (family 23 vs 25; baseline AMD EPYC" in text
    )
    for same in (again, older):  # the same identity; a manifest that names only the model
        code, out, err = cli("gate", "--baseline", str(rome), "--candidate", str(same))
        assert code == 0 and "not comparable" not in out, out + err
