"""The compensation service (pipeline/serve.py) with real XML-RPC clients: answers the model
verifies, a Fault naming the field for every bad request, and the server keeps serving.

On the trained artifacts of conftest's `trained_project` (the project's own after `dvc repro`).
"""
import copy
import socket
import subprocess
import sys
import threading
import time
import xmlrpc.client
from pathlib import Path

import numpy as np
import pytest
import torch

from pipeline.lib.artifacts import load_points
from pipeline.lib.columns import JOINTS_DEG, THEORY
from pipeline.lib.config import load_params
from pipeline.lib.training import load_model
from conftest import ENV, project_points
from pipeline.serve import make_server, url

ROOT = Path(__file__).resolve().parents[1]
@pytest.fixture(scope="module")
def project(trained_project):
    """The project root with trained artifacts (the working directory for the module's tests)."""
    with pytest.MonkeyPatch.context() as mp:
        mp.chdir(trained_project)
        yield trained_project


@pytest.fixture(scope="module")
def params(project):
    return load_params()


@pytest.fixture(scope="module")
def poses(project, params):
    """Test-split points: recorded angles (rad) and their theory positions (mm), as compensate uses them."""
    df = project_points(params)
    df = df[df.split == "test"]
    return np.radians(df[JOINTS_DEG].to_numpy()), df[THEORY].to_numpy()


def serving(params, host="127.0.0.1", port=0):
    server = make_server(params, host, port)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server


@pytest.fixture(scope="module")
def server(params):
    s = serving(params)
    yield s
    s.shutdown()
    s.server_close()


@pytest.fixture()
def client(server):
    return xmlrpc.client.ServerProxy(url(server))


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_compensate_lands_on_a_test_target(client, params, poses):
    q0, target = poses[0][0].tolist(), poses[1][0].tolist()
    r = client.compensate(q0, target)
    tol = params["compensate"]["tol_mm"]
    assert set(r) == {"q_rad", "residual_mm", "converged", "in_workspace"}
    assert len(r["q_rad"]) == 6 and all(isinstance(v, float) for v in r["q_rad"])
    assert r["converged"] is True and r["residual_mm"] < tol
    assert isinstance(r["in_workspace"], bool)
    with torch.no_grad():                                  # the model, evaluated on its own, agrees
        p = load_model("models/boter.pt")(torch.tensor([r["q_rad"]], dtype=torch.float64))[0][0].numpy()
    assert np.linalg.norm(p - target) < tol
    assert not np.allclose(r["q_rad"], q0)                 # it had something to correct
    flat = client.compensate_list(q0, target)              # the URScript form: the same answer, flat
    assert flat == r["q_rad"] + [r["residual_mm"], 1.0, float(r["in_workspace"])]


def test_compensate_many_equals_single_calls(client, poses):
    q0, target = poses[0][:20].tolist(), poses[1][:20].tolist()
    many = client.compensate_many([[a, b] for a, b in zip(q0, target)])
    assert many == [client.compensate(a, b) for a, b in zip(q0, target)]
    assert len(many) == 20 and all(r["converged"] for r in many)
    assert client.compensate_many([]) == []


def test_concurrent_clients_get_their_own_answers(server, poses):
    q0, target = poses[0][:16].tolist(), poses[1][:16].tolist()
    expected = xmlrpc.client.ServerProxy(url(server)).compensate_many([[a, b] for a, b in zip(q0, target)])
    out = [None] * 16

    def call(i):
        out[i] = xmlrpc.client.ServerProxy(url(server)).compensate(q0[i], target[i])
    threads = [threading.Thread(target=call, args=(i,)) for i in range(16)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert out == expected


BAD = {  # name: (call on a proxy given a good q0 and target, words the fault must contain)
    "5 angles": (lambda c, q, t: c.compensate(q[:5], t), ["q_rad", "expected 6 numbers, got 5"]),
    "4 target numbers": (lambda c, q, t: c.compensate(q, t + [1.0]), ["target_mm", "expected 3 numbers, got 4"]),
    "nan": (lambda c, q, t: c.compensate(q, [t[0], float("nan"), t[2]]), ["target_mm[1]", "not a finite number (nan)"]),
    "inf": (lambda c, q, t: c.compensate(q[:3] + [float("inf")] + q[4:], t), ["q_rad[3]", "not a finite number (inf)"]),
    "a string angle": (lambda c, q, t: c.compensate(q[:2] + ["1.0"] + q[3:], t), ["q_rad[2]", "expected a number",
                                                                                  "string"]),
    "a string target": (lambda c, q, t: c.compensate(q, "1,2,3"), ["target_mm", "expected a list of 3 numbers"]),
    "a struct": (lambda c, q, t: c.compensate({"x": 1.0}, t), ["q_rad", "struct"]),
    "a boolean": (lambda c, q, t: c.compensate(q, [True, 0.0, 0.0]), ["target_mm[0]", "boolean"]),
    "beyond the joint limits": (lambda c, q, t: c.compensate(q[:2] + [float(np.radians(400.0))] + q[3:], t),
                                ["q_rad[2]", "400.0°", "6.981 rad", "beyond the joint limits [-360, 360]°"]),
    "10 m away": (lambda c, q, t: c.compensate(q, [10000.0, 0.0, 0.0]), ["target_mm", "unreachable", "10000.0 mm"]),
    "inside the base": (lambda c, q, t: c.compensate(q, [0.0, 0.0, 0.0]), ["target_mm", "unreachable", "residual",
                                                                           "tolerance 0.001 mm"]),
    "unknown method": (lambda c, q, t: c.compensate_all(q, t), ["compensate_all", "unknown method"]),
    "missing argument": (lambda c, q, t: c.compensate(q), ["compensate", "q_rad, target_mm", "got 1"]),
    "bad item in a batch": (lambda c, q, t: c.compensate_many([[q, t], [q, t], [q, t], [q, t[:2]]]),
                            ["requests[3].target_mm", "expected 3 numbers, got 2"]),
    "bad pair in a batch": (lambda c, q, t: c.compensate_many([[q, t], [q]]), ["requests[1]", "[q_rad, target_mm]"]),
    "unreachable in a batch": (lambda c, q, t: c.compensate_many([[q, t], [q, [0.0, 0.0, 9000.0]]]),
                               ["requests[1].target_mm", "unreachable"]),
    "batch not a list": (lambda c, q, t: c.compensate_many(42), ["requests", "expected a list"]),
}


@pytest.mark.parametrize("name", list(BAD))
def test_bad_request_is_a_fault_naming_the_field_and_the_server_keeps_serving(client, poses, name):
    call, words = BAD[name]
    q0, target = poses[0][0].tolist(), poses[1][0].tolist()
    with pytest.raises(xmlrpc.client.Fault) as e:
        call(client, q0, target)
    for w in words:
        assert w in e.value.faultString, e.value.faultString
    assert client.compensate(q0, target)["converged"]      # still serving


def test_close_but_not_converged_is_an_answer_far_is_a_fault(params, poses):
    """Joints held within ±0.001° of q0: a target 0.3 mm off is answered, unconverged; 5 mm off is a Fault."""
    q0 = poses[0][0]
    p = copy.deepcopy(params)
    p["robot"]["joint_limits_deg"] = [[a - 1e-3, a + 1e-3] for a in np.degrees(q0)]
    p["compensate"]["max_iter"] = 50                       # the full solver stalls here: no need for 500 steps
    server = serving(p)
    try:
        c = xmlrpc.client.ServerProxy(url(server))
        with torch.no_grad():
            at_q0 = load_model("models/boter.pt")(torch.tensor(q0[None]))[0][0].numpy()
        r = c.compensate(q0.tolist(), (at_q0 + [0.3, 0.0, 0.0]).tolist())
        assert r["converged"] is False and 0.2 < r["residual_mm"] < p["serve"]["unreachable_mm"]
        assert np.abs(np.degrees(r["q_rad"]) - np.degrees(q0)).max() <= 1e-3 + 1e-9
        with pytest.raises(xmlrpc.client.Fault, match=r"target_mm: unreachable \(residual [45]\.\d mm"):
            c.compensate(q0.tolist(), (at_q0 + [0.0, 5.0, 0.0]).tolist())
    finally:
        server.shutdown()
        server.server_close()


def test_refuses_to_start_without_trained_artifacts(params, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as e:
        make_server(params, "127.0.0.1", 0)
    msg = str(e.value.code)
    assert "models/boter.pt" in msg and "models/workspace.json" in msg and "dvc repro" in msg
    assert "calibration.json" not in msg and "frame.json" not in msg      # the checkpoint carries its geometry


def test_serve_only_on_rpc2(server):
    with pytest.raises(xmlrpc.client.ProtocolError, match="404"):
        xmlrpc.client.ServerProxy(url(server).removesuffix("/RPC2") + "/other").system.listMethods()


def test_the_command_serves(project, poses):
    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "pipeline.serve", "--port", str(port)], cwd=project, env=ENV,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        c, deadline = xmlrpc.client.ServerProxy(f"http://127.0.0.1:{port}/RPC2"), time.monotonic() + 60
        while True:
            try:
                methods = c.system.listMethods()
                break
            except OSError:
                assert proc.poll() is None and time.monotonic() < deadline, "the server did not start"
                time.sleep(0.2)
        assert {"compensate", "compensate_many", "compensate_list"} <= set(methods)
        assert c.compensate(poses[0][1].tolist(), poses[1][1].tolist())["converged"]
    finally:
        proc.terminate()
        out = proc.communicate(timeout=30)[0]
    assert f"http://127.0.0.1:{port}/RPC2" in out and "compensate_many" in out
