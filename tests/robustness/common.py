"""What the robustness tests share: running a command through the command-line boundary and
reading its one line."""
import sys

from mi_nerfpp.commands import cli

TINY = ['--iterations', '2', '--batch-rays', '32', '--samples', '4', '4', '4',
        '--grid-levels', '4', '8', '--preview-every', '0', '--checkpoint-every', '0']


def run_cli(capsys, *argv):
    """Run a command in-process through the command-line boundary: (status, stdout, stderr)."""
    try:
        status = cli.main([str(a) for a in argv])
    except SystemExit as e:      # argparse errors
        status = e.code if isinstance(e.code, int) else 1
        if not isinstance(e.code, int) and e.code is not None:
            print(e.code, file=sys.stderr)
    out, err = capsys.readouterr()
    return status, out, err


def one_clear_line(err):
    """The only line of ``err`` (none else, no traceback)."""
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and 'Traceback' not in err, err
    return lines[0]


def error_line(err, command):
    """The one ``error: <command>: ...`` line of a command that failed after showing progress
    (progress bars above it), with no traceback; returns what follows the prefix."""
    assert 'Traceback' not in err, err
    errors = [line for line in err.splitlines() if line.startswith('error:')]
    assert len(errors) == 1 and err.rstrip().endswith(errors[0]), err
    prefix = f'error: {command}: '
    assert errors[0].startswith(prefix), errors[0]
    return errors[0][len(prefix):]


class Training:
    """``optimize`` in a child process on a tiny configuration that trains for ever
    (``--iterations 100000``), its stderr collected as it comes, so that a test can wait until
    training steps run - not for a time that a loaded machine may not keep - and then signal
    it. ``sigint``: the SIGINT disposition the child starts with (SIG_IGN: as a background
    job of a script is started)."""

    ITERATIONS = 100000

    def __init__(self, capture, out, *extra, sigint=None):
        import signal
        import subprocess
        import threading
        sigint = signal.SIG_DFL if sigint is None else sigint
        self.proc = subprocess.Popen(
            [sys.executable, '-m', 'mi_nerfpp', 'optimize', str(capture), '--out', str(out),
             '--iterations', str(self.ITERATIONS), '--batch-rays', '32', '--samples', '4', '4',
             '4', '--grid-levels', '4', '8', '--preview-every', '0', '--checkpoint-every', '0',
             *map(str, extra)],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE,
            preexec_fn=lambda: signal.signal(signal.SIGINT, sigint))
        self.chunks = []
        self.out = []
        self.reader = threading.Thread(target=self._read, args=(self.proc.stderr, self.chunks),
                                       daemon=True)
        self.reader.start()
        self.out_reader = threading.Thread(target=self._read, args=(self.proc.stdout, self.out),
                                           daemon=True)
        self.out_reader.start()

    @staticmethod
    def _read(stream, into):
        while True:
            chunk = stream.read1(4096) if hasattr(stream, 'read1') else stream.read(4096)
            if not chunk:
                return
            into.append(chunk)

    @property
    def stderr(self):
        return b''.join(self.chunks).decode(errors='replace')

    def iterations(self):
        """The last iteration count the progress bar showed (0 before the first)."""
        import re
        counts = re.findall(rf'(\d+)/{self.ITERATIONS}', self.stderr)
        return int(counts[-1]) if counts else 0

    def wait_for_steps(self, steps=1, timeout=600):
        """Wait until the progress bar shows ``steps`` steps done (the signal handlers of
        training are set from the first step on)."""
        import time
        deadline = time.monotonic() + timeout
        while self.iterations() < steps:
            assert self.proc.poll() is None, f'training ended early:\n{self.stderr}'
            assert time.monotonic() < deadline, f'no training steps in {timeout} s'
            time.sleep(0.1)

    def stop(self, sig, timeout=120):
        """Send ``sig`` and wait for the end: (status, stderr)."""
        self.proc.send_signal(sig)
        try:
            self.proc.wait(timeout)
        finally:
            if self.proc.poll() is None:
                self.proc.kill()
                self.proc.wait()
        self.reader.join(10)
        return self.proc.returncode, self.stderr

    def kill(self):
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()
