"""Timings carry the CPU they ran on: model, family/model numbers and the widest vector unit."""
from lumibench.machine import cpu_description


def _cpuinfo(tmp_path, model: int, flags: str) -> str:
    block = (f"processor\t: {{p}}\nvendor_id\t: AuthenticAMD\ncpu family\t: 25\nmodel\t\t: {model}\n"
             f"model name\t: AMD EPYC\nflags\t\t: {flags}\n\n")
    path = tmp_path / f"cpuinfo_{model}"
    path.write_text(block.format(p=0) + block.format(p=1))
    return str(path)


def test_two_boxes_with_the_same_model_name_are_told_apart(tmp_path):
    milan = cpu_description(_cpuinfo(tmp_path, 1, "fpu sse avx avx2 fma"))
    genoa = cpu_description(_cpuinfo(tmp_path, 17, "fpu avx2 avx512f avx512bw avx512_bf16"))
    assert milan == "AMD EPYC (family 25 model 1, AVX2)"
    assert genoa == "AMD EPYC (family 25 model 17, AVX-512 BF16)"
    assert cpu_description(_cpuinfo(tmp_path, 2, "fpu avx2 avx512f")).endswith("AVX-512)")
    assert cpu_description(str(tmp_path / "absent"))  # not Linux: still a name


def test_training_timings_name_the_cpu():
    import torch

    from method.devices import device_name

    assert device_name(torch.device("cpu")) == cpu_description()
