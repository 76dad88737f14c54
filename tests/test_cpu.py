"""CPU features that decide whether full-range INT8 weights run exactly (pipeline/cpu.py)."""

import os
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


def test_a_cgroup_cpu_quota_bounds_the_usable_cpus(tmp_path, monkeypatch):
    """A container limited to N CPUs (docker --cpus, a Kubernetes limit) still sees every host core in its
    affinity mask; the quota in cgroup v2's cpu.max or v1's cfs files bounds what the runtime sizes its
    threads by."""
    from pipeline import cpu

    v2 = tmp_path / "v2"
    v2.mkdir()
    (v2 / "cpu.max").write_text("150000 100000\n")
    assert cpu.cpu_quota(v2) == 1.5
    (v2 / "cpu.max").write_text("max 100000\n")
    assert cpu.cpu_quota(v2) is None
    v1 = tmp_path / "v1" / "cpu"
    v1.mkdir(parents=True)
    (v1 / "cpu.cfs_quota_us").write_text("200000\n")
    (v1 / "cpu.cfs_period_us").write_text("100000\n")
    assert cpu.cpu_quota(v1.parent) == 2.0
    (v1 / "cpu.cfs_quota_us").write_text("-1\n")
    assert cpu.cpu_quota(v1.parent) is None
    assert cpu.cpu_quota(tmp_path / "none") is None
    (v2 / "cpu.max").write_text("40000 100000\n")  # 0.4 of a CPU: still one thread
    monkeypatch.setattr(cpu, "CGROUP", v2)
    assert cpu.usable_cpus() == 1
    (v2 / "cpu.max").write_text("max 100000\n")
    assert cpu.usable_cpus() == len(os.sched_getaffinity(0))


def test_worker_shares_keep_smt_siblings_together(tmp_path):
    """On an SMT box Linux numbers a core's two threads i and i + N: cut in id order, two workers of a 2-core,
    4-thread box got CPUs 0, 1 and 2, 3, each worker one thread of both cores. Shares are whole cores."""
    from pipeline.cpu import core_shares, physical_cores

    for cpu, core in enumerate((0, 1, 0, 1)):  # CPUs 0 and 2 are core 0's threads, 1 and 3 core 1's
        topology = tmp_path / f"cpu{cpu}" / "topology"
        topology.mkdir(parents=True)
        (topology / "physical_package_id").write_text("0\n")
        (topology / "core_id").write_text(f"{core}\n")
    assert physical_cores([0, 1, 2, 3], tmp_path) == [[0, 2], [1, 3]]
    assert core_shares([0, 1, 2, 3], 2, tmp_path) == [[0, 2], [1, 3]]
    assert core_shares([0, 1, 2, 3], 1, tmp_path) == [[0, 2, 1, 3]]
    assert core_shares([0, 1, 2, 3], 4, tmp_path) == [[0], [1], [2], [3]]  # more shares than cores: threads
    # No topology to read (another OS, a sandbox): each CPU a core of its own, cut in id order.
    assert core_shares([0, 1, 2, 3], 2, tmp_path / "none") == [[0, 1], [2, 3]]
    # This machine: every CPU in exactly one share.
    cpus = sorted(os.sched_getaffinity(0))
    assert sorted(cpu for share in core_shares(cpus, 1) for cpu in share) == cpus
