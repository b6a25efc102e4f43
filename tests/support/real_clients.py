"""Real `openpi-client` scripts (run in the client venv, `client_env`) that tests drive our server with: the script
prelude, sending observations on one connection, and several clients sending at once."""

from __future__ import annotations

import json
import subprocess
import urllib.error
import urllib.request
from pathlib import Path
from typing import Any

import numpy as np
from client_env import collect, spawn_client

from openpi_cam.serving import msgpack_numpy

# Runs in the client venv (numpy 1.x, openpi_client 0.1.x). argv[1] is a JSON object of arguments.
CLIENT_PRELUDE = r"""
import json, sys
import msgpack
import numpy as np
from openpi_client import msgpack_numpy, websocket_client_policy

ARGS = json.loads(sys.argv[1])

def connect(api_key=None):
    return websocket_client_policy.WebsocketClientPolicy(host="127.0.0.1", port=ARGS["port"], api_key=api_key)

# The random observations of upstream's examples/simple_client, drawn from a seeded generator.
def droid_obs(rng, size=(224, 224)):
    return {
        "observation/exterior_image_1_left": rng.randint(256, size=(*size, 3), dtype=np.uint8),
        "observation/wrist_image_left": rng.randint(256, size=(*size, 3), dtype=np.uint8),
        "observation/joint_position": rng.rand(7),
        "observation/gripper_position": rng.rand(1),
        "prompt": "do something",
    }

def libero_obs(rng):
    return {
        "observation/state": rng.rand(8),
        "observation/image": rng.randint(256, size=(224, 224, 3), dtype=np.uint8),
        "observation/wrist_image": rng.randint(256, size=(224, 224, 3), dtype=np.uint8),
        "prompt": "do something",
    }

def aloha_obs(rng):
    cams = ("cam_high", "cam_low", "cam_left_wrist", "cam_right_wrist")
    return {
        "state": np.ones((14,)),
        "images": {c: rng.randint(256, size=(3, 224, 224), dtype=np.uint8) for c in cams},
        "prompt": "do something",
    }

OBSERVATIONS = {"droid": droid_obs, "libero": libero_obs, "aloha": aloha_obs}

def write(path, obj):
    # Packed with the client's own msgpack_numpy: the test decodes these bytes with ours.
    with open(path, "wb") as f:
        f.write(msgpack_numpy.packb(obj))

def read(path):
    with open(path, "rb") as f:
        return msgpack_numpy.unpackb(f.read())

def wait_for_peers(barrier, me, peers, timeout=60.0):
    # Every client connects first, then all send at once, so that their requests overlap at the server.
    import os, time
    open(os.path.join(barrier, f"ready{me}"), "w").close()
    deadline = time.time() + timeout
    while len(os.listdir(barrier)) < peers:
        if time.time() > deadline:
            raise TimeoutError(f"only {len(os.listdir(barrier))} of {peers} clients connected")
        time.sleep(0.005)

class RawPacker:
    def __init__(self, payload):
        self.payload = payload
    def pack(self, obs):
        return self.payload

def infer_raw(policy, payload):
    # Sends `payload` as is (bytes: binary frame, str: text frame) through the real client's infer().
    packer, policy._packer = policy._packer, RawPacker(payload)
    try:
        return policy.infer({})
    finally:
        policy._packer = packer

def error_of(fn):
    try:
        fn()
    except Exception as e:
        return f"{type(e).__name__}: {e}"
    return None

def done(**result):
    print(json.dumps(result))
"""

# Sends the observations packed in ARGS["observations"] (file paths) in order on one connection; writes each
# response and, for byte comparisons, the response without its timings as the client's own packer writes it.
SEND = r"""
policy = connect()
write(ARGS["out"] + "/metadata.msgpack", policy.get_server_metadata())
if ARGS.get("barrier"):
    wait_for_peers(ARGS["barrier"], ARGS["client"], ARGS["clients"])
keys = []
for i, path in enumerate(ARGS["observations"]):
    response = policy.infer(read(path))
    write(ARGS["out"] + f"/response{i}.msgpack", response)
    write(ARGS["out"] + f"/untimed{i}.msgpack", {k: v for k, v in response.items() if not k.endswith("_timing")})
    keys.append(list(response))
done(keys=keys)
"""

ROUND_TRIP = r"""
policy = connect()
write(ARGS["out"] + "/metadata.msgpack", policy.get_server_metadata())
rng = np.random.RandomState(ARGS["seed"])
for i in range(ARGS["n"]):
    obs = OBSERVATIONS[ARGS["env"]](rng)
    response = policy.infer(obs)
    write(ARGS["out"] + f"/obs{i}.msgpack", obs)
    write(ARGS["out"] + f"/response{i}.msgpack", response)
done(n=ARGS["n"])
"""


def client_script(body: str) -> str:
    return CLIENT_PRELUDE + body


def read_packed(path: Path) -> Any:
    return msgpack_numpy.unpackb(path.read_bytes())


def round_trip(port: int, out: Path, *, env: str = "droid", seed: int = 0, n: int = 1) -> subprocess.Popen:
    out.mkdir(parents=True, exist_ok=True)
    args = json.dumps({"port": port, "out": str(out), "env": env, "seed": seed, "n": n})
    return spawn_client(client_script(ROUND_TRIP), args)


def send_observations(
    port: int, out: Path, observations: list[dict], *, barrier: Path | None = None, client: int = 0, clients: int = 1
) -> subprocess.Popen:
    """Starts a real client that sends `observations` (packed here with our packer, which writes the client's
    bytes) one after the other on one connection; finish it with `collect`, read the answers with `responses`."""
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for i, obs in enumerate(observations):
        path = out / f"obs{i}.msgpack"
        path.write_bytes(msgpack_numpy.packb(obs))
        paths.append(str(path))
    args = {"port": port, "out": str(out), "observations": paths, "client": client, "clients": clients}
    if barrier is not None:
        args["barrier"] = str(barrier)
    return spawn_client(client_script(SEND), json.dumps(args))


def responses(out: Path, n: int) -> list[dict]:
    return [read_packed(out / f"response{i}.msgpack") for i in range(n)]


N_CLIENTS = 4  # even: the swapping server below pairs connections 0/1 and 2/3
REQUESTS_PER_CLIENT = 3


def serve_concurrent_clients(port: int, tmp_path: Path, observations: list[dict]) -> list[list[np.ndarray]]:
    """N real clients connect, wait for each other, then each sends REQUESTS_PER_CLIENT observations (client i sends
    observations[(i + j) % 4] as its j-th, so that at every round each client sends a different one). -> the
    actions each client received, per client and request."""
    barrier = tmp_path / "barrier"
    barrier.mkdir()
    procs = [
        send_observations(
            port,
            tmp_path / f"client{i}",
            [observations[(i + j) % len(observations)] for j in range(REQUESTS_PER_CLIENT)],
            barrier=barrier,
            client=i,
            clients=N_CLIENTS,
        )
        for i in range(N_CLIENTS)
    ]
    for proc in procs:
        collect(proc)
    return [[r["actions"] for r in responses(tmp_path / f"client{i}", REQUESTS_PER_CLIENT)] for i in range(N_CLIENTS)]


def wrong_answers(received: list[list[np.ndarray]], alone: list[np.ndarray]) -> list[tuple[int, int]]:
    """(client, request) of every answer that is not its observation's own (served alone)."""
    return [
        (i, j)
        for i, answers in enumerate(received)
        for j, actions in enumerate(answers)
        if not np.array_equal(actions, alone[(i + j) % len(alone)])
    ]


def http_get(url: str, headers: dict[str, str] | None = None, timeout: float = 5.0) -> tuple[int, str]:
    request = urllib.request.Request(url, headers=headers or {})
    try:
        with urllib.request.urlopen(request, timeout=timeout) as response:
            return response.status, response.read().decode()
    except urllib.error.HTTPError as e:
        return e.code, e.read().decode()


def get_stats(port: int, headers: dict[str, str] | None = None) -> dict:
    status, body = http_get(f"http://127.0.0.1:{port}/stats", headers)
    assert status == 200, body
    return json.loads(body)
