"""Drive bus layer of hexacnc: CANopen CiA 402 drives on one or more CAN buses.

Modules (one job each):

* :mod:`drivers.layout`   - which node sits on which bus, PDO COB-IDs and mappings per layout
* :mod:`drivers.busload`  - worst-case bus time per cycle; refuses layouts over ``[bus] max_load``
* :mod:`drivers.canbus`   - open the python-can bus(es): socketcan, virtual, udp_multicast (echo filtered)
* :mod:`drivers.cia402`   - CiA 402 state machine tables (tagged by transition number), EMCY texts
* :mod:`drivers.description` - drive descriptions (EDS/DCF) per node: identity, [DummyUsage], 0x60C2 range
* :mod:`drivers.commission` - identity check, 0x60C2 format, units (factor group), reactions (read back)
* :mod:`drivers.master`   - CANopen master for the non-cyclic work (boot, SDO mapping, enable/disable)
* :mod:`drivers.scan`     - ``hexacnc bus scan``: every node on the bus and whether it matches the config
* :mod:`drivers.pcap`     - SocketCAN pcap capture (``hexacnc run --capture``); :mod:`drivers.pcapcheck` (tshark)
* :mod:`drivers.busdemand` - bus demand per cycle, staggered vs uniform timers (``hexacnc bus demand``)
* :mod:`drivers.cyclic`   - the hot-path codec (prebuilt frames, ``struct``), no allocation per cycle
* :mod:`drivers.simdrive` - six simulated CiA 402 drives (the config glue and the process: :mod:`hexacnc.sim.drives`)
* :mod:`drivers.simnode`  - one simulated drive node (PDOs, state machine, supervision, fault injection)
* :mod:`drivers.simreact` - simulated reactions: stop ramps (0x605A/0x605C/0x605E), comm loss (0x6007, 0x1029)
* :mod:`drivers.simhooks` - object-dictionary hooks for simulated extensions (homing, touch probe)
* :mod:`drivers.simfaults` - fault injection specs
* :mod:`drivers.strutmodel` - pluggable strut dynamics for the simulated drives
* :mod:`drivers.testing`  - private network namespaces (cross-process bus tests), an independent PDO decoder

Nothing here imports ``hexacnc`` (``hexacnc bench arch``: layer violations 0).

``hexapod_drive.eds`` is the default description of the drives (real and simulated, profile
``permissive``); ``strict_drive.eds`` the simulated ``strict`` profile.
"""
from __future__ import annotations

from pathlib import Path

#: path of the EDS shipped with the package
EDS_PATH = Path(__file__).resolve().parent / "hexapod_drive.eds"

__all__ = ["EDS_PATH"]
