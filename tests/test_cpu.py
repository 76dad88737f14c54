"""CPU features that decide whether full-range INT8 weights run exactly (pipeline/cpu.py)."""

from pathlib import Path

from pipeline.cpu import SPEED_FLAGS, cpu_flags, describe, has_vnni, int8_pairs_saturate, is_x86, speed_flags


def test_vnni_in_any_of_its_flags():
    assert has_vnni(frozenset({"avx2", "avx512f", "avx512_vnni"}))
    assert has_vnni(frozenset({"avx2", "avx_vnni"}))  # Alder Lake and later: VEX-encoded VNNI
    assert not has_vnni(frozenset({"avx2", "fma", "avx512f", "avx512bw"}))  # Skylake-SP, AMD Zen 3
    assert not has_vnni(frozenset())


def test_saturation_is_an_x86_without_vnni_matter():
    assert not int8_pairs_saturate(frozenset({"avx2", "avx512_vnni"}))
    assert int8_pairs_saturate(frozenset({"avx2", "fma"})) == is_x86()  # Arm's dot products never do


def test_flags_read_from_proc_cpuinfo():
    flags = cpu_flags()
    if Path("/proc/cpuinfo").exists() and is_x86():
        assert "sse2" in flags  # every x86-64 CPU
    assert isinstance(flags, frozenset)


def test_speed_flags_keep_their_order_and_only_the_known_ones():
    assert speed_flags(frozenset({"sse2", "avx512_vnni", "avx2", "fma"})) == ["avx2", "fma", "avx512_vnni"]
    assert set(speed_flags()) <= set(SPEED_FLAGS)


def test_a_report_names_the_cpu_and_what_its_int8_does():
    report = describe()
    assert report["cpu"] and report["cpu_flags"] == speed_flags()
    if is_x86() and Path("/proc/cpuinfo").exists():  # e.g. "family 25 model 17", the first processor's numbers
        first = Path("/proc/cpuinfo").read_text().split("\n\n")[0]
        info = {key.strip(): value.strip() for key, _, value in (line.partition(":") for line in first.splitlines())}
        assert report["cpu_generation"] == f"family {info['cpu family']} model {info['model']}"
    assert report["int8_pair_sums_saturate"] == int8_pairs_saturate()
