"""Ray: an address where no Ray cluster answers ends ``video --ray`` and ``sweep --ray`` with one
line, before any work, instead of Ray's client retrying for ever. Real Ray: a refused port, a
port that accepts and says nothing, a server of another protocol, and a gRPC server that is
no Ray cluster (which Ray's client would wait on for ever: the command gives up after
MI_NERFPP_RAY_TIMEOUT seconds). The commands run in child processes with a timeout, so a hang
fails the test instead of stalling the suite. The working cluster is
tests/jobs/test_cluster.py's."""
import os
import socket
import subprocess
import sys
import threading

import pytest

from mi_nerfpp.jobs import cluster
from tests.robustness.common import one_clear_line, run_cli

pytest.importorskip('ray')


def command(*argv, env=None, timeout=240):
    """Run ``python -m mi_nerfpp ARGV``: (status, stderr); a hang is a failure."""
    proc = subprocess.run([sys.executable, '-m', 'mi_nerfpp', *map(str, argv)],
                          capture_output=True, text=True, timeout=timeout,
                          env=dict(os.environ, **(env or {})))
    return proc.returncode, proc.stderr


def refused_port():
    """A local port where nothing listens."""
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


class Server:
    """A local TCP server that answers each connection with ``reply`` (None: says nothing)
    and keeps it open."""

    def __init__(self, reply=None):
        self.socket = socket.socket()
        self.socket.bind(('0.0.0.0', 0))
        self.socket.listen(16)
        self.port = self.socket.getsockname()[1]
        self.reply, self.connections = reply, []
        threading.Thread(target=self._serve, daemon=True).start()

    def _serve(self):
        while True:
            try:
                connection, _ = self.socket.accept()
            except OSError:
                return
            self.connections.append(connection)
            if self.reply is not None:
                try:
                    connection.recv(100)
                    connection.sendall(self.reply)
                except OSError:
                    pass

    def close(self):
        for c in self.connections:
            c.close()
        self.socket.close()


NO_CLUSTER = ('no Ray cluster answers there (connection refused): start one with `ray start '
              '--head` and give the address it prints, or use --ray auto')


def test_video_on_an_address_where_nothing_listens_is_one_line(tiny_run, tmp_path):
    """`video --ray 127.0.0.1:1` retried for ever."""
    status, err = command('video', tiny_run, '--ray', '127.0.0.1:1', '-o', tmp_path / 'v.gif',
                          '--frames', '2')
    assert status == 1 and one_clear_line(err) == f'error: video: --ray 127.0.0.1:1: {NO_CLUSTER}'
    assert list(tmp_path.iterdir()) == []


def test_sweep_on_an_address_where_nothing_listens_is_one_line(capture, tmp_path):
    """`sweep --ray 127.0.0.1:1` retried for ever."""
    port = refused_port()
    status, err = command('sweep', capture, '--out', tmp_path / 'sweep', '--ray',
                          f'127.0.0.1:{port}', '--iterations', '1')
    assert status == 1 and one_clear_line(err) == (
        f'error: sweep: --ray 127.0.0.1:{port}: {NO_CLUSTER}')
    assert not (tmp_path / 'sweep').exists()


def test_auto_with_a_ray_address_of_nothing_is_one_line(capsys, capture, tmp_path, monkeypatch):
    monkeypatch.setenv('RAY_ADDRESS', '127.0.0.1:1')
    status, _, err = run_cli(capsys, 'sweep', capture, '--out', tmp_path / 'sweep', '--ray')
    assert status == 1 and one_clear_line(err) == (
        f'error: sweep: --ray auto (RAY_ADDRESS=127.0.0.1:1): {NO_CLUSTER}')


@pytest.mark.parametrize('reply, message', [
    (None, 'no Ray cluster answers there (no answer within 1 s): start one with `ray start '
           '--head` and give the address it prints, or use --ray auto'),
    (b'HTTP/1.1 400 Bad Request\r\n\r\n', 'something answers there, but not a Ray cluster (no '
                                          'gRPC reply): give the address `ray start --head` '
                                          'prints, or use --ray auto'),
])
def test_an_address_that_does_not_answer_like_ray_is_refused(capsys, tiny_run, tmp_path,
                                                             monkeypatch, reply, message):
    monkeypatch.setattr(cluster, 'CONNECT_TIMEOUT', 1.0)
    server = Server(reply)
    try:
        status, _, err = run_cli(capsys, 'video', tiny_run, '--ray', f'127.0.0.1:{server.port}',
                                 '-o', tmp_path / 'v.gif', '--frames', '2')
    finally:
        server.close()
    assert status == 1 and one_clear_line(err) == (
        f'error: video: --ray 127.0.0.1:{server.port}: {message}')


@pytest.mark.parametrize('address', ['nohost', 'host:0', 'host:port'])
def test_an_address_that_is_not_one_is_refused(capsys, tiny_run, tmp_path, address):
    status, _, err = run_cli(capsys, 'video', tiny_run, '--ray', address, '-o',
                             tmp_path / 'v.gif')
    assert status == 1 and one_clear_line(err) == (
        f"error: video: --ray {address}: not a cluster address: give HOST:PORT (the head "
        f"node's address, as `ray start --head` prints it) or auto")


def test_a_grpc_server_that_is_no_cluster_times_out(capture, tmp_path):
    """It answers the HTTP/2 preface like a Ray head would, then nothing: Ray's client waits
    on it for ever, out of reach of Python's signal handlers; the command gives up."""
    server = Server(bytes([0, 0, 0, 4, 0, 0, 0, 0, 0]))     # an empty HTTP/2 SETTINGS frame
    try:
        status, err = command('sweep', capture, '--out', tmp_path / 'sweep', '--ray',
                              f'127.0.0.1:{server.port}', '--iterations', '1',
                              env={'MI_NERFPP_RAY_TIMEOUT': '5'})
    finally:
        server.close()
    lines = [line for line in err.splitlines() if line.startswith('error:')]
    assert status == 1 and 'Traceback' not in err and lines == [
        f'error: sweep: --ray 127.0.0.1:{server.port}: no Ray cluster came up there within '
        f'5 s (something answers, but Ray cannot join it): check the address `ray start '
        f'--head` printed, or use --ray auto']
