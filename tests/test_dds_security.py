"""DDS Security: step_executor run with authentication, access control and encryption from a keystore that
launch_scripts/create_keystore.sh makes with openssl (SROS2 layout), probed by rustdds participants
(`patchwalk_dds_probe`) with and without credentials, and by rclpy.

The Fast DDS of the PyPI ROS 2 wheels is built without its security plugins, so the credentialed side is
tested between rustdds participants; rclpy here is an unauthenticated participant (which must see nothing).
"""

from __future__ import annotations

import json
import os
import subprocess
import time

import pytest

import patchwalk_testing as pw

KEYSTORE_SCRIPT = pw.REPO / "launch_scripts" / "create_keystore.sh"


@pytest.fixture(scope="module")
def keystore(tmp_path_factory):
    path = tmp_path_factory.mktemp("keystore")
    subprocess.run([str(KEYSTORE_SCRIPT), str(path), "/patchwalk/step_executor", "/patchwalk/operator",
                    "/patchwalk/watcher=observer"], check=True, capture_output=True, text=True, timeout=120)
    return path


def secure(keystore, enclave: str) -> dict[str, str]:
    return {"ROS_SECURITY_ENABLE": "true", "ROS_SECURITY_STRATEGY": "Enforce", "ROS_SECURITY_KEYSTORE": str(keystore),
            "ROS_SECURITY_ENCLAVE_OVERRIDE": enclave}


def probe(env: dict[str, str], *args: str, timeout: float = 90.0) -> dict:
    unsecured = {k: v for k, v in os.environ.items() if not k.startswith("ROS_SECURITY_")}
    done = subprocess.run([str(pw.binary("patchwalk_dds_probe")), *args], env={**unsecured, **env},
                          capture_output=True, text=True, timeout=timeout, cwd=pw.REPO)
    assert done.returncode == 0, f"probe exited with {done.returncode}:\n{done.stderr}"
    assert "panicked" not in done.stderr, done.stderr
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_keystore_has_the_sros2_layout_and_verifies(keystore):
    for name in ("public/ca.cert.pem", "public/identity_ca.cert.pem", "public/permissions_ca.cert.pem",
                 "private/ca.key.pem", "enclaves/governance.xml", "enclaves/governance.p7s"):
        assert (keystore / name).exists(), name
    ca = keystore / "public" / "ca.cert.pem"
    for enclave in ("patchwalk/step_executor", "patchwalk/operator", "patchwalk/watcher"):
        d = keystore / "enclaves" / enclave
        for name in ("cert.pem", "key.pem", "identity_ca.cert.pem", "permissions_ca.cert.pem", "governance.p7s", "permissions.p7s"):
            assert (d / name).is_file(), (enclave, name)
        assert (d / "key.pem").read_text().startswith("-----BEGIN PRIVATE KEY-----")  # PKCS#8
        subprocess.run(["openssl", "verify", "-CAfile", str(ca), str(d / "cert.pem")], check=True, capture_output=True)
        subprocess.run(["openssl", "smime", "-verify", "-in", str(d / "permissions.p7s"), "-CAfile", str(ca)],
                       check=True, capture_output=True)
        subject = subprocess.run(["openssl", "x509", "-in", str(d / "cert.pem"), "-noout", "-subject"],
                                 check=True, capture_output=True, text=True).stdout
        assert f"/{enclave}" in subject, subject
    watcher = (keystore / "enclaves" / "patchwalk" / "watcher" / "permissions.xml").read_text()
    assert "<subscribe><topics><topic>*</topic>" in watcher
    assert "<publish><topics><topic>*</topic>" not in watcher and "rq/" not in watcher


def test_only_credentialed_participants_see_a_secured_executor(ros, start_node, keystore):
    from patchwalk_msgs.msg import ExecutorStatus
    executor = start_node("step_executor", "--param", "ros.status_rate_hz=20",
                          env=secure(keystore, "/patchwalk/step_executor"))
    # An operator with valid credentials sees the (encrypted) status.
    operator = probe(secure(keystore, "/patchwalk/operator"), "--seconds", "60", "--no-calls", "--until-answered")
    assert operator["status_messages"] > 0, operator
    assert "DDS Security on" in executor.log()
    # No credentials: nothing is seen, nothing is answered.
    nobody = probe({}, "--seconds", "10")
    assert nobody == {"status_messages": 0, "arm": {"answered": False, "success": False, "message": ""},
                      "play_motion": {"answered": False, "success": False, "message": ""}}, nobody
    # Valid identity with read-only permissions: sees the status; its own access control refuses the
    # writer of an arm request.
    watcher = probe(secure(keystore, "/patchwalk/watcher"), "--seconds", "60", "--no-calls", "--until-answered")
    assert watcher["status_messages"] > 0, watcher
    unsecured = {k: v for k, v in os.environ.items() if not k.startswith("ROS_SECURITY_")}
    refused = subprocess.run([str(pw.binary("patchwalk_dds_probe")), "--seconds", "5"],
                             env={**unsecured, **secure(keystore, "/patchwalk/watcher")},
                             capture_output=True, text=True, timeout=60, cwd=pw.REPO)
    assert refused.returncode != 0
    assert "Not allowed to create a DataWriter to topic rq/step_executor/armRequest" in refused.stderr, refused.stderr
    # rclpy (Fast DDS without security plugins) is unauthenticated too: no status reaches it. (Whether a
    # service looks ready is no proof either way: endpoints of nodes killed by earlier tests on this
    # domain stay in rclpy's discovery cache until their lease ends.)
    status = ros.collect(ExecutorStatus, "/step_executor/status")
    time.sleep(3.0)
    assert not status.messages
    assert executor.alive()


def test_an_operator_with_credentials_can_arm_play_and_stop(start_node, keystore):
    start_node("step_executor", "--param", "ros.status_rate_hz=20", env=secure(keystore, "/patchwalk/step_executor"))
    operator = probe(secure(keystore, "/patchwalk/operator"), "--seconds", "60", "--until-answered", "--stop")
    # Both calls reach the executor and are answered by it: arm is refused without a heartbeat on the
    # deadman topic, play_motion because the test's executor has no servo bus.
    assert operator["arm"]["answered"] and operator["play_motion"]["answered"], operator
    assert "heartbeat" in operator["arm"]["message"], operator
    assert operator["play_motion"]["message"].startswith('play_motion("probe")'), operator
    # The e-stop of a secured operator latches: its answer, then the encrypted status shows it.
    assert operator["stop"]["answered"] and operator["stop"]["success"], operator
    assert operator["estopped"], operator


def test_secured_stop_first_call_and_round_trips(start_node, keystore):
    """A fresh secured operator's e-stop: the first call after the service is ready, then 50 more one
    after the other (figures printed with pytest -s). The probe fails if any call is unanswered within
    its 60 s; the bound on the first call is the 3 s a request lost to an unfinished key exchange
    would cost (it is resent on the writer's next periodic heartbeat)."""
    start_node("step_executor", env=secure(keystore, "/patchwalk/step_executor"))
    timing = probe(secure(keystore, "/patchwalk/operator"), "--seconds", "60", "--time-stop", "50")
    print(f"secured stop: ready after {timing['ready_ms']:.0f} ms, first call {timing['first_call_ms']:.1f} ms, "
          f"then p50 {timing['round_trip_ms']['p50']:.2f} ms, max {timing['round_trip_ms']['max']:.2f} ms "
          f"over {timing['round_trip_ms']['calls']} calls")
    assert timing["round_trip_ms"]["calls"] == 50
    assert timing["first_call_ms"] < 3000.0, timing


def test_enforce_refuses_to_start_without_the_enclave_files(keystore, tmp_path):
    env = {**os.environ, **secure(keystore, "/patchwalk/nobody")}
    done = subprocess.run([str(pw.binary("step_executor")), "run"], env=env, capture_output=True, text=True,
                          timeout=60, cwd=pw.REPO)
    assert done.returncode != 0
    out = done.stdout + done.stderr
    assert "/patchwalk/nobody" in out and "identity_ca.cert.pem" in out, out
    assert "panicked" not in out, out
