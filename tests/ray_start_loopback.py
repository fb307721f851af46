"""``ray start`` that keeps 127.0.0.1 as the node address, for a second node on one machine.

Ray's CLI turns 127.0.0.1 into the machine's network address
(``ray._private.services.resolve_ip_for_localhost``), and then binds its servers to every
interface, unless ``RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0``, which in turn makes ``ray start
--address`` refuse to add a node. This wrapper keeps the address as given and runs the real CLI:
``python tests/ray_start_loopback.py start --address 127.0.0.1:PORT --node-ip-address 127.0.0.1``.
"""

import sys

import ray._private.services as services
from ray.scripts.scripts import main

services.resolve_ip_for_localhost = lambda host: host

if __name__ == "__main__":
    sys.argv = ["ray", *sys.argv[1:]]
    main()
