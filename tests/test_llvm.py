"""libLLVM discovery: picks a version >= 17, refuses old ones with a clear message."""
import os
import subprocess
import sys

import pytest

from mi_nerfpp import _llvm


@pytest.mark.parametrize('path, version', [
    ('/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1', 19),
    ('/usr/lib/x86_64-linux-gnu/libLLVM-15.so.1', 15),
    ('/usr/lib/x86_64-linux-gnu/libLLVM-17.so', 17),
    ('/usr/lib/llvm-18/lib/libLLVM.so.1', 18),
    ('/opt/homebrew/opt/llvm/lib/libLLVM.20.dylib', 20),
    ('/somewhere/libLLVM.so', None),
])
def test_version_parsing(path, version):
    assert _llvm.llvm_version(path) == version


def _fake_libs(tmp_path, names):
    for n in names:
        (tmp_path / n).write_bytes(b'')
    return [str(tmp_path / 'libLLVM*.so*')]


def test_configure_picks_newest_supported(tmp_path):
    patterns = _fake_libs(tmp_path, ['libLLVM-14.so.1', 'libLLVM-15.so.1', 'libLLVM.so.19.1',
                                     'libLLVM-17.so.1'])
    env = {}
    path = _llvm.configure(env, patterns)
    assert path == str(tmp_path / 'libLLVM.so.19.1') and env['DRJIT_LIBLLVM_PATH'] == path


def test_configure_without_usable_llvm_names_package(tmp_path):
    patterns = _fake_libs(tmp_path, ['libLLVM-14.so.1', 'libLLVM-15.so.1', 'libLLVM-16.so.1'])
    with pytest.raises(_llvm.LLVMNotFoundError, match='apt-get install -y libllvm19') as e:
        _llvm.configure({}, patterns)
    assert 'libLLVM-16.so.1 (16)' in str(e.value)


def test_configure_respects_user_path_but_refuses_old_version(tmp_path):
    new = tmp_path / 'libLLVM.so.18.1'
    new.write_bytes(b'')
    assert _llvm.configure({'DRJIT_LIBLLVM_PATH': str(new)}, []) == str(new)
    old = tmp_path / 'libLLVM-15.so.1'
    old.write_bytes(b'')
    with pytest.raises(_llvm.LLVMNotFoundError, match='is LLVM 15'):
        _llvm.configure({'DRJIT_LIBLLVM_PATH': str(old)}, [])
    with pytest.raises(_llvm.LLVMNotFoundError, match='does not exist'):
        _llvm.configure({'DRJIT_LIBLLVM_PATH': str(tmp_path / 'gone.so')}, [])


def _python(code, **env):
    full = {k: v for k, v in os.environ.items() if k != 'DRJIT_LIBLLVM_PATH'}
    full.update(env)
    return subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, env=full,
                          timeout=120)


def test_import_finds_llvm_by_itself_and_renders():
    r = _python('import mi_nerfpp, os, mitsuba as mi, drjit as dr;'
                'print(mi.variant(), os.environ["DRJIT_LIBLLVM_PATH"]);'
                'print(dr.sum(dr.arange(mi.Float, 10)))')
    assert r.returncode == 0, r.stderr
    variant, path = r.stdout.split()[:2]
    assert variant == 'llvm_ad_rgb' and _llvm.llvm_version(path) >= 17
    assert '[45]' in r.stdout


def test_import_keeps_a_variant_chosen_by_the_caller_and_refuses_non_ad():
    r = _python('import mitsuba as mi; mi.set_variant("scalar_rgb"); import mi_nerfpp')
    assert r.returncode != 0 and "needs a differentiable RGB Mitsuba variant" in r.stderr
