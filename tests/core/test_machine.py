"""The machine's description that benchmarks print and the server logs."""

from __future__ import annotations

from service.core.machine import cpu_description, describe_cpuinfo

ZEN4 = """processor\t: 0
model name\t: AMD EPYC 9654 96-Core Processor
cpu family\t: 25
model\t\t: 17
flags\t\t: fpu avx avx2 fma avx512f avx512_vnni

processor\t: 1
model name\t: another name
cpu family\t: 1
flags\t\t: fpu
"""


def test_a_cpu_with_avx512_vnni_is_named_with_its_features_from_its_first_processor() -> None:
    line = describe_cpuinfo(ZEN4, cores=4)
    assert line == "AMD EPYC 9654 96-Core Processor (family 25, model 17), 4 cores; AVX2, FMA, AVX-512, AVX-512 VNNI"


def test_a_cpu_without_vector_units_says_what_it_lacks() -> None:
    line = describe_cpuinfo("model name : old\nflags : fpu sse\n", cores=1)
    assert line == "old, 1 core; no AVX2; no AVX-512, no VNNI"
    assert describe_cpuinfo("model name : x\nflags : avx2 avx_vnni\n", cores=2).endswith("AVX2, AVX-VNNI; no AVX-512")


def test_this_machine_is_described_without_error() -> None:
    line = cpu_description()
    assert isinstance(line, str) and "core" in line


def test_an_arm_cpu_is_described_by_its_own_features_and_no_x86_ones() -> None:
    text = ("processor : 0\nBogoMIPS : 50.00\nFeatures : fp asimd asimddp i8mm\n"
            "CPU implementer : 0x41\nCPU part : 0xd0c\n")
    line = describe_cpuinfo(text, cores=8)
    assert line == "Arm CPU (implementer 0x41, part 0xd0c), 8 cores; NEON, dot product, int8 matrix"


def test_text_that_names_no_cpu_gives_the_fallback_name_and_the_cores() -> None:
    assert describe_cpuinfo("", cores=2, fallback_name="x86_64") == "x86_64, 2 cores"
