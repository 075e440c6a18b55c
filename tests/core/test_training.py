from lerobot_condground.core.training import amp_flags, native_bf16, speed_flags


def test_bf16_autocast_only_where_the_cpu_multiplies_bf16_natively(tmp_path):
    """Autocast on an AVX2-only CPU made a training step 23 times slower: AMX or AVX-512 BF16 turn it on."""
    cpuinfo = tmp_path / "cpuinfo"
    cpuinfo.write_text("flags\t\t: fpu sse avx2 avx512f avx512_bf16 amx_bf16 amx_tile amx_int8\n")
    assert amp_flags(cpuinfo) == ["--policy.use_amp=true"]
    cpuinfo.write_text("flags\t\t: fpu sse avx2 avx512f avx512_bf16 avx512_vnni\n")
    assert amp_flags(cpuinfo) == ["--policy.use_amp=true"]
    cpuinfo.write_text("flags\t\t: fpu sse avx2 avx512f avx512_vnni\n")
    assert amp_flags(cpuinfo) == []
    cpuinfo.write_text("flags\t\t: fpu sse avx2 fma\n")
    assert amp_flags(cpuinfo) == []
    assert amp_flags(tmp_path / "absent") == []


def test_native_bf16_is_amx_or_avx512_bf16(tmp_path):
    """bf16 is only faster than fp32 where the CPU multiplies it natively: AMX tiles or AVX-512 BF16 (Zen 4)."""
    cpuinfo = tmp_path / "cpuinfo"
    for flags, native in (
        ("fpu sse avx2 avx512f avx512_bf16 amx_bf16 amx_tile", True),
        ("fpu sse avx2 avx512f avx512_bf16 avx512_vnni", True),
        ("fpu sse avx2 avx512f avx512_vnni", False),
        ("fpu sse avx2 fma", False),
    ):
        cpuinfo.write_text(f"flags\t\t: {flags}\n")
        assert native_bf16(cpuinfo) is native, flags
    assert native_bf16(tmp_path / "absent") is False


def test_speed_flags_are_channels_last_and_bf16_where_amp_turns_it_on(tmp_path):
    cpuinfo = tmp_path / "cpuinfo"
    cpuinfo.write_text("flags\t\t: fpu sse avx2 fma\n")
    assert speed_flags(cpuinfo) == ["--policy.channels_last=true"]
    cpuinfo.write_text("flags\t\t: fpu avx512f avx512_bf16 amx_bf16 amx_tile\n")
    assert speed_flags(cpuinfo) == ["--policy.channels_last=true", "--policy.use_amp=true"]
