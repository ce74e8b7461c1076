"""The attacker of a handshake flood, shared by ``handshake_flood.py`` and its test.

``ATTACKER`` is a whole program, run in its own process: it keeps argv[3] connections open to
argv[1]:argv[2] until the file argv[5] exists (at most argv[6] seconds), reopening each one
the server closes at once; with argv[4] == "hello" each sends a HELLO (no token: it never
gets further). It prints "flooding" once the server has closed one, and at the end how many
the server closed.
"""

ATTACKER = """
import os, selectors, socket, sys, time
from evclock.remote import _protocol as proto
host, port, width = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
how, stop, seconds = sys.argv[4], sys.argv[5], float(sys.argv[6])
sel = selectors.DefaultSelector()
closed = 0
announced = False
end = time.monotonic() + seconds
while time.monotonic() < end and not os.path.exists(stop):
    while len(sel.get_map()) < width and not os.path.exists(stop):
        try:
            sock = socket.create_connection((host, port), timeout=1)
            if how == "hello":
                sock.sendall(proto.hello(proto.MODE_FOLLOW, "attacker", proto.new_nonce()))
        except OSError:
            continue
        sock.setblocking(False)
        sel.register(sock, selectors.EVENT_READ)
    for key, _ in sel.select(0.05):
        try:
            data = key.fileobj.recv(65536)
        except OSError:
            data = b""
        if data and how == "hello" and data[4] == proto.CHALLENGE:
            continue  # its challenge: it never answers
        sel.unregister(key.fileobj)
        key.fileobj.close()  # refused or evicted: open another at once
        closed += 1
        if not announced:
            announced = True
            print("flooding", flush=True)
print(closed, flush=True)
"""
