"""Where a step's time goes (mi_nerfpp.core.profiling): kernels attributed to the stage that
launched them, and the work each does estimated from Dr.Jit's kernel history."""
import drjit as dr
import mitsuba as mi
import numpy as np

from mi_nerfpp.core.profiling import KernelProfile, stage, streamed_bytes

N = 1 << 16


def test_a_kernel_counts_in_its_stage_with_its_operations_and_streamed_bytes():
    """``c = a·b + 3`` over N floats reads a and b and writes c whole (12 bytes an element; the
    scalar 3 is read once); a gather of N/2 floats from a writes its N/2 results whole and
    reads a only in part (4 bytes an element counted)."""
    a = dr.arange(mi.Float, N)
    b = dr.arange(mi.Float, N) * 2
    dr.eval(a, b)
    with KernelProfile() as profile:
        with stage('fma'):
            c = dr.fma(a, b, dr.opaque(mi.Float, 3.0))
            dr.eval(c)
        with stage('gather'):
            g = dr.gather(mi.Float, a, dr.arange(mi.UInt32, N // 2) * 2)
            dr.eval(g)
    work = profile.by_stage_work()
    ms, launches, ops, nbytes = work[('fma', 'kernels')]
    assert launches == 1 and ms >= 0
    assert nbytes == 12 * N
    assert ops >= 2 * N and ops % N == 0           # IR operations per element, times N
    _, launches, _, nbytes = work[('gather', 'kernels')]
    assert launches == 1 and nbytes == 4 * (N // 2)
    np.testing.assert_array_equal(np.array(c)[:3], [3.0, 5.0, 11.0])
    np.testing.assert_array_equal(np.array(g)[:3], [0.0, 2.0, 4.0])


def test_streamed_bytes_reads_vector_loads_and_stores_by_type():
    ir = '\n'.join(['%a = load <8 x float>, ptr %p', '%b = load <8 x i8>, ptr %q',
                    'store <8 x double> %c, ptr %r', '%s = load float, ptr %t',
                    '%g = call <8 x float> @llvm.masked.gather.v8f32(<8 x ptr> %u, i32 4)',
                    'call void @llvm.masked.store.v16f32(<16 x float> %v, ptr %w)'])
    assert streamed_bytes(ir) == 4 + 1 + 8 + 4
