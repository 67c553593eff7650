"""Serves one ``policy_env.PickPlaceEnv`` over stdin/stdout; run by the simulator's venv.

    SIMENV/bin/python env_server.py SIM_TOOLS_DIR

Requests and replies are pickled tuples, each behind its 8-byte length. Requests: ``("open", source,
kwargs)``, ``("reset", seed)``, ``("reset", None, (x, y, yaw))`` (the object at that pose),
``("step", action)``, ``("evaluate",)``, ``("close",)``. Replies: ``("ok", value)`` or
``("error", text)``. Anything the environment prints goes to stderr."""

import os
import pickle
import struct
import sys
import traceback


def _read(stream):
    header = stream.read(8)
    if len(header) < 8:
        return None
    (size,) = struct.unpack("<Q", header)
    return pickle.loads(stream.read(size))


def _write(stream, value):
    data = pickle.dumps(value, protocol=4)
    stream.write(struct.pack("<Q", len(data)) + data)
    stream.flush()


def main():
    sys.path.insert(0, sys.argv[1])
    os.environ.setdefault("MUJOCO_GL", "osmesa")
    requests, replies = sys.stdin.buffer, sys.stdout.buffer
    sys.stdout = sys.stderr
    import policy_env

    env = None
    while True:
        request = _read(requests)
        if request is None or request[0] == "close":
            break
        try:
            if request[0] == "open":
                env = policy_env.PickPlaceEnv.from_episode(request[1], **request[2])
                value = {"fps": env.fps, "max_steps": env.max_steps}
            elif request[0] == "reset":
                value = env.reset(seed=request[1], object_pose=request[2] if len(request) > 2 else None)
            elif request[0] == "step":
                value = env.step(request[1])
            elif request[0] == "evaluate":
                value = env.evaluate()
            else:
                raise ValueError("unknown request %r" % (request[0],))
            _write(replies, ("ok", value))
        except Exception:  # the client raises it with the server's traceback
            _write(replies, ("error", traceback.format_exc()))
    if env is not None:
        env.close()


if __name__ == "__main__":
    main()
