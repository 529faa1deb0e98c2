"""Choosing the backend (mi_nerfpp.variant): the caller's variant, then MI_NERFPP_VARIANT, then
llvm_ad_rgb; ``--variant`` on the command line; the one-line errors of a variant mi_nerfpp does
not run on and of CUDA without a driver or GPU (run here, on the CPU, where there is none); and
the path that replaces ``drjit.nn``'s packed networks on CUDA, checked on the CPU."""
import os
import subprocess
import sys

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from mi_nerfpp import variant
from mi_nerfpp.commands import cli
from mi_nerfpp.core import fields
from mi_nerfpp.data.synth import scene_file
from tests.robustness.common import one_clear_line, run_cli

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
HAS_CUDA = bool(dr.has_backend(dr.JitBackend.CUDA))
HAS_LLVM = bool(dr.has_backend(dr.JitBackend.LLVM))
CURRENT = mi.variant()          # this process's: MI_NERFPP_VARIANT's (the GPU check), or the CPU
needs_no_cuda = pytest.mark.skipif(HAS_CUDA, reason='this machine runs CUDA: no error to see')
needs_llvm = pytest.mark.skipif(not HAS_LLVM, reason="no libLLVM: Dr.Jit's CPU backend is off")
NO_CUDA = 'cuda_ad_rgb was asked for ({}) but no CUDA driver/GPU was found: '


def _env(**changes):
    env = {k: v for k, v in os.environ.items() if k not in ('MI_NERFPP_VARIANT',
                                                            'MI_NERFPP_DEBUG')}
    env['PYTHONPATH'] = os.pathsep.join(p for p in (ROOT, env.get('PYTHONPATH')) if p)
    env.update(changes)
    return env


def _python(args, timeout=180, **env):
    return subprocess.run([sys.executable, *args], capture_output=True, text=True,
                          env=_env(**env), timeout=timeout, cwd=ROOT)


def _small_render(tmp_path):
    return [scene_file('render_random.xml'), '-o', str(tmp_path / 'out.exr'),
            '-D', 'res_x=6', '-D', 'res_y=4']


# ------------------------------------------------------------------------------ the choice

def test_the_choice_is_the_callers_variant_then_the_variable_then_the_cpu():
    assert variant.choose(None, {}) == ('llvm_ad_rgb', 'default')
    assert variant.choose(None, {'MI_NERFPP_VARIANT': ' '}) == ('llvm_ad_rgb', 'default')
    assert variant.choose(None, {'MI_NERFPP_VARIANT': 'cuda_ad_rgb'}) == \
        ('cuda_ad_rgb', 'MI_NERFPP_VARIANT')
    assert variant.choose('llvm_ad_rgb', {'MI_NERFPP_VARIANT': 'cuda_ad_rgb'}) == \
        ('llvm_ad_rgb', 'mi.set_variant')
    # The command line's --variant: over the variable, under the caller's; argparse refuses
    # what it does not know.
    env = {'MI_NERFPP_VARIANT': 'cuda_ad_rgb'}
    assert variant.choose(None, env, 'llvm_ad_rgb') == ('llvm_ad_rgb', '--variant')
    assert variant.choose(None, env, 'cuda') == ('cuda_ad_rgb', 'MI_NERFPP_VARIANT')
    assert variant.choose('llvm_ad_rgb', {}, 'cuda_ad_rgb') == ('llvm_ad_rgb', 'mi.set_variant')


def test_the_variant_option_is_read_from_the_command_line():
    assert variant.option_value(['-m', '--variant', 'cuda_ad_rgb', 'render']) == 'cuda_ad_rgb'
    assert variant.option_value(['-m', 'render', 'x', '--variant=llvm_ad_rgb']) == 'llvm_ad_rgb'
    assert variant.option_value(['-m', '--variant', 'a', 'render', '--variant', 'b']) == 'b'
    assert variant.option_value(['-m', 'sweep', '--', '--variant', 'cuda_ad_rgb']) is None
    assert variant.option_value(['-m', 'render', '--variant']) is None


def test_a_variant_it_does_not_run_on_is_refused_naming_the_choices():
    with pytest.raises(variant.VariantError) as e:
        variant.choose(None, {'MI_NERFPP_VARIANT': 'llvm_ad_spectral'})
    assert str(e.value) == ("MI_NERFPP_VARIANT='llvm_ad_spectral' is not a variant mi_nerfpp runs "
                            "on: set it to one of llvm_ad_rgb (the CPU), cuda_ad_rgb (an NVIDIA "
                            "GPU), or unset it for llvm_ad_rgb")
    with pytest.raises(variant.VariantError, match="but 'scalar_rgb' is selected"):
        variant.choose('scalar_rgb', {})
    assert issubclass(variant.VariantError, ImportError)


def test_the_command_line_is_told_from_a_library_import():
    assert variant.command_line(['-m', 'render', 'x.xml']) == (True, 'render')
    assert variant.command_line(['/usr/bin/mi-nerfpp', '--debug', '--variant', 'cuda_ad_rgb',
                                 'optimize', 'data']) == (True, 'optimize')
    assert variant.command_line(['optimize.py', '--steps']) == (True, 'optimize')
    assert variant.command_line(['-m', '--variant']) == (True, None)
    assert variant.command_line(['-c']) == (False, None)
    assert variant.command_line(['script.py', 'render']) == (False, None)
    assert variant.command_line([]) == (False, None)


@needs_llvm
def test_the_variable_selects_the_cpu_and_the_callers_variant_wins():
    r = _python(['-c', 'import mi_nerfpp, mitsuba as mi; print(mi.variant())'],
                MI_NERFPP_VARIANT='llvm_ad_rgb')
    assert r.returncode == 0 and r.stdout.split() == ['llvm_ad_rgb'], r.stderr
    # Selected before the import: MI_NERFPP_VARIANT is not even checked for CUDA.
    r = _python(['-c', 'import mitsuba as mi; mi.set_variant("llvm_ad_rgb"); import mi_nerfpp; '
                       'print(mi.variant(), type(mi.load_dict({"type": "nerfpp"})).__name__)'],
                MI_NERFPP_VARIANT='cuda_ad_rgb')
    assert r.returncode == 0 and r.stdout.split() == ['llvm_ad_rgb', 'NeRFPPIntegrator'], r.stderr


@needs_llvm
def test_a_bad_variable_fails_the_import_and_the_command_line_in_one_line():
    r = _python(['-c', 'import mi_nerfpp'], MI_NERFPP_VARIANT='gpu')
    assert r.returncode == 1 and r.stderr.rstrip().splitlines()[-1] == (
        "mi_nerfpp.variant.VariantError: MI_NERFPP_VARIANT='gpu' is not a variant mi_nerfpp "
        "runs on: set it to one of llvm_ad_rgb (the CPU), cuda_ad_rgb (an NVIDIA GPU), or unset "
        "it for llvm_ad_rgb")
    r = _python(['-m', 'mi_nerfpp', 'render', 'scene.xml'], MI_NERFPP_VARIANT='gpu')
    assert r.returncode == 1 and r.stdout == ''
    assert one_clear_line(r.stderr).startswith(
        "error: render: MI_NERFPP_VARIANT='gpu' is not a variant mi_nerfpp runs on")


# ------------------------------------------------------------------------------ CUDA missing

@needs_no_cuda
@needs_llvm
def test_cuda_without_a_driver_fails_the_import_with_a_variant_error():
    r = _python(['-c', 'import mi_nerfpp'], MI_NERFPP_VARIANT='cuda_ad_rgb')
    assert r.returncode == 1
    assert r.stderr.rstrip().splitlines()[-1].startswith(
        'mi_nerfpp.variant.VariantError: ' + NO_CUDA.format('MI_NERFPP_VARIANT'))
    r = _python(['-c', 'import mi_nerfpp.variant as v; print(v.check_available("llvm_ad_rgb", '
                       '"x")); v.check_available("cuda_ad_rgb", "--variant")'])
    assert r.stdout.split() == ['None'] and NO_CUDA.format('--variant') in r.stderr


@needs_no_cuda
@pytest.mark.parametrize('program', [['-m', 'mi_nerfpp', 'optimize', 'data'],
                                     [os.path.join(ROOT, 'optimize.py'), 'data']])
def test_cuda_without_a_driver_ends_the_command_line_in_one_line(program):
    r = _python(program, MI_NERFPP_VARIANT='cuda_ad_rgb')
    assert r.returncode == 1 and r.stdout == ''
    line = one_clear_line(r.stderr)
    assert line.startswith('error: optimize: ' + NO_CUDA.format('MI_NERFPP_VARIANT')), line
    assert line.endswith('To run on the CPU, unset MI_NERFPP_VARIANT (or set it to '
                         'llvm_ad_rgb); for the GPU, install the NVIDIA driver on a machine '
                         'with an NVIDIA GPU'), line
    r = _python(program + ['--debug'], MI_NERFPP_VARIANT='cuda_ad_rgb')
    assert r.returncode == 1 and 'Traceback' in r.stderr
    assert r.stderr.rstrip().splitlines()[-1] == line


# ------------------------------------------------------------------------------ --variant

def test_variant_option_before_or_after_the_command(tmp_path, capsys):
    status, out, err = run_cli(capsys, '--variant', CURRENT, 'render', *_small_render(tmp_path))
    assert status == 0 and 'wrote' in out, err
    status, out, err = run_cli(capsys, 'render', *_small_render(tmp_path), '--variant', CURRENT)
    assert status == 0 and 'wrote' in out, err


def test_a_bad_variant_option_is_a_usage_error(capsys):
    status, _, err = run_cli(capsys, '--variant', 'scalar_rgb', 'render', 'x.xml')
    assert status == 2 and "argument --variant: invalid choice: 'scalar_rgb'" in err
    r = _python(['-m', 'mi_nerfpp', 'render', 'x.xml', '--variant', 'cuda'])
    assert r.returncode == 2 and "argument --variant: invalid choice: 'cuda'" in r.stderr


@needs_llvm
def test_the_variant_option_is_passed_on_to_the_processes_a_command_starts():
    code = ('import os, sys; sys.argv = ["-m", "render", "--variant", "llvm_ad_rgb"]\n'
            'import mi_nerfpp, mitsuba as mi\n'
            'print(mi.variant(), os.environ["MI_NERFPP_VARIANT"])')
    r = _python(['-c', code], MI_NERFPP_VARIANT='cuda_ad_rgb')
    assert r.returncode == 0 and r.stdout.split() == ['llvm_ad_rgb', 'llvm_ad_rgb'], r.stderr


@needs_llvm
def test_the_variant_option_wins_over_the_variable(tmp_path):
    r = _python(['-m', 'mi_nerfpp', 'render', *_small_render(tmp_path), '--variant',
                 'llvm_ad_rgb'], MI_NERFPP_VARIANT='cuda_ad_rgb')
    assert r.returncode == 0 and r.stdout.startswith('wrote'), r.stderr


@needs_no_cuda
def test_the_cuda_option_needs_no_libllvm():
    """On a GPU machine without libLLVM, --variant cuda_ad_rgb must get as far as CUDA: here,
    with libLLVM hidden, it ends at the missing driver, not at libLLVM."""
    r = _python(['-m', 'mi_nerfpp', '--variant', 'cuda_ad_rgb', 'render', 'x.xml'],
                DRJIT_LIBLLVM_PATH=os.path.join(ROOT, 'no-libLLVM.so'))
    assert r.returncode == 1 and r.stdout == '' and 'Traceback' not in r.stderr
    # Above the line: Dr.Jit's own words on the missing libLLVM.
    assert r.stderr.rstrip().splitlines()[-1].startswith(
        'error: render: ' + NO_CUDA.format('--variant')), r.stderr


@needs_no_cuda
def test_variant_option_cuda_without_a_driver_is_one_line(capsys):
    status, out, err = run_cli(capsys, '--variant', 'cuda_ad_rgb', 'render', 'x.xml')
    assert status == 1 and out == ''
    assert one_clear_line(err).startswith('error: render: ' + NO_CUDA.format('--variant'))
    r = _python(['-m', 'mi_nerfpp', 'render', 'x.xml', '--variant', 'cuda_ad_rgb'])
    assert r.returncode == 1 and r.stdout == ''
    line = one_clear_line(r.stderr)
    assert line.startswith('error: render: ' + NO_CUDA.format('--variant'))
    assert 'leave out --variant cuda_ad_rgb (or pass --variant llvm_ad_rgb)' in line


class _Elsewhere:
    """Stands in for ``mitsuba`` in :mod:`mi_nerfpp.commands.cli`: a process that selected
    cuda_ad_rgb (this machine has no GPU to select it for real)."""
    @staticmethod
    def variant():
        return 'cuda_ad_rgb'


def test_another_variant_from_python_says_to_choose_it_before_the_import(monkeypatch, capsys):
    monkeypatch.setattr(cli, 'mi', _Elsewhere)
    status, out, err = run_cli(capsys, '--variant', 'llvm_ad_rgb', 'render', 'x.xml')
    assert status == 1 and one_clear_line(err) == (
        'error: render: --variant llvm_ad_rgb: this process runs cuda_ad_rgb, selected when '
        'mi_nerfpp was imported, and a process keeps its variant: set '
        "MI_NERFPP_VARIANT=llvm_ad_rgb (or call mi.set_variant('llvm_ad_rgb')) before "
        'importing mi_nerfpp')


@needs_llvm
def test_another_variant_on_the_command_line_runs_the_command_anew_in_it(monkeypatch, tmp_path):
    calls = []
    monkeypatch.setattr(cli, 'mi', _Elsewhere)
    monkeypatch.setattr(os, 'execve', lambda *a: calls.append(a) or sys.exit(7))
    monkeypatch.setattr(sys, 'argv', ['mi-nerfpp', 'render', 'x.xml', '--variant', 'llvm_ad_rgb'])
    with pytest.raises(SystemExit):
        cli.main()
    (path, args, env), = calls
    assert path == sys.executable and env['MI_NERFPP_VARIANT'] == 'llvm_ad_rgb'
    assert args == [sys.executable, '-m', 'mi_nerfpp', 'render', 'x.xml', '--variant',
                    'llvm_ad_rgb']
    # For real: the process is replaced by `python -m mi_nerfpp ...`, which renders.
    code = ('import sys; from mi_nerfpp.commands import cli\n'
            'class Elsewhere:\n    variant = staticmethod(lambda: "cuda_ad_rgb")\n'
            'cli.mi = Elsewhere\n'
            f'sys.argv = ["mi-nerfpp", "--variant", "llvm_ad_rgb", "render", '
            f'*{_small_render(tmp_path)!r}]\n'
            'cli.main()\nprint("not replaced")\n')
    r = _python(['-c', code])
    assert r.returncode == 0, r.stderr
    assert r.stdout.startswith(f'wrote {tmp_path / "out.exr"}') and 'not replaced' not in r.stdout


# ------------------------------------------------------------------------------ packed networks

@pytest.mark.skipif(not CURRENT.startswith('llvm'), reason='packed networks: the CPU only '
                    '(on CUDA, benchmarks/gpu_check.py tries them in a process of their own)')
def test_tensor_mode_renders_what_packed_networks_render(tiny_scene, monkeypatch):
    """CUDA renders with the networks in tensor mode (mitsuba3 issue 1825); on the CPU, inside
    the integrator, the image equals that of the packed networks the CPU uses."""
    assert fields.PACKED_INFERENCE == (os.environ.get('MI_NERFPP_PACKED', '1') != '0')
    monkeypatch.setattr(fields, 'PACKED_INFERENCE', True)
    packed = np.array(mi.render(tiny_scene, spp=2, seed=3))
    monkeypatch.setattr(fields, 'PACKED_INFERENCE', False)
    tensor = np.array(mi.render(tiny_scene, spp=2, seed=3))
    assert np.all(np.isfinite(tensor)) and tensor.std() > 0
    np.testing.assert_allclose(tensor, packed, rtol=1e-4, atol=1e-5)
