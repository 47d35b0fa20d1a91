"""tools/gpu_kernel_check.py (the residual's element-wise path on a GPU) runs its stages on the CPU too:
there the float64 rows of both calls are the compiled ones, the float32 rows the element-wise ones."""

import torch
from tool_support import load_tool

CPU = torch.device("cpu")


def test_parity_and_gradient_stages_on_the_cpu():
    check = load_tool("gpu_kernel_check")
    parity = check.parity(CPU, 300)
    assert set(parity) == {"mono_float64", "mono_float32", "stereo_float64", "stereo_float32"}
    for name, stage in parity.items():
        assert stage["valid_rows"] > 250 and stage["valid_disagree"] == 0, name
        bound = 0.0 if name.endswith("float64") else 1e-5  # float32 keeps about 7 digits
        assert all(stage[k] <= bound for k in check.OUTPUTS), (name, stage)
    grad = check.gradient(CPU, 300)
    assert grad["max_abs_difference"] <= 1e-12 * grad["scale"]
    timing = check.timing(CPU, 64, 1)
    assert timing["forward"]["median_ms"] > 0 and timing["forward_backward"]["median_ms"] > 0
