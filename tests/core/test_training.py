from lerobot_condground.core.training import amp_flags


def test_bf16_autocast_only_where_the_cpu_has_amx_tiles(tmp_path):
    """Autocast on an AVX2-only CPU made a training step 23 times slower: it is turned on by AMX alone."""
    cpuinfo = tmp_path / "cpuinfo"
    cpuinfo.write_text("flags\t\t: fpu sse avx2 avx512f avx512_bf16 amx_bf16 amx_tile amx_int8\n")
    assert amp_flags(cpuinfo) == ["--policy.use_amp=true"]
    cpuinfo.write_text("flags\t\t: fpu sse avx2 fma\n")
    assert amp_flags(cpuinfo) == []
    assert amp_flags(tmp_path / "absent") == []
