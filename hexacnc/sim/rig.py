"""Master and simulated drives of a config on private ``virtual`` buses, in one process (unit tests).

The config-to-drives glue (:mod:`hexacnc.sim.drives`) is in ``hexacnc``; the cross-process helpers
(network namespaces) and the independent frame decoder stay in :mod:`drivers.testing`.
"""
from __future__ import annotations


class SimRig:
    """Master and simulated drives on private ``virtual`` buses, in one process (unit tests).

    ``SimRig(cfg=None, faults=(), **bus_changes)``: ``cfg`` defaults to the embedded default machine;
    ``bus_changes`` replace ``[bus]`` fields (``layout="single"``, ``buses=1`` ...; ``comm_loss_timeout_s``
    defaults to 0.5 s here). The channel is
    made unique per rig. ``rig.master`` (attached), ``rig.sim`` (started), ``rig.cyclic()`` detaches
    the master and returns a :class:`drivers.cyclic.CyclicIO` on the master's buses.
    """

    def __init__(self, cfg=None, *, faults=(), model_factory=None, **bus_changes):
        import dataclasses
        import uuid

        from drivers.canbus import open_buses
        from drivers.master import Master

        from ..config import load_config
        from .drives import sim_drives

        cfg = cfg if cfg is not None else load_config()
        # master and drives share this process (and its GIL) on a shared test machine: the drives'
        # master supervision (RPDO deadline) gets 0.5 s unless a test asks for less
        changes = {"interface": "virtual", "channel": f"rig-{uuid.uuid4().hex[:10]}", "comm_loss_timeout_s": 0.5,
                   **bus_changes}
        self.cfg = cfg.replace(bus=dataclasses.replace(cfg.bus, **changes))
        self.sim_buses = open_buses(self.cfg.bus)
        self.master_buses = open_buses(self.cfg.bus)
        self.sim = sim_drives(self.cfg, self.sim_buses, faults=faults, model_factory=model_factory).start()
        self.master = Master(self.cfg, self.master_buses)
        self.io = None

    def cyclic(self, **kw):
        from drivers.cyclic import CyclicIO, limits_inc

        kw.setdefault("sync_every", self.master.sync_every)
        if self.master.attached:
            kw.setdefault("status", self.master.statuswords())
            kw.setdefault("positions_inc", self.master.positions_inc())
        self.master.detach()
        kw.setdefault("limits_inc", limits_inc(self.cfg))
        kw.setdefault("period_s", self.cfg.cycle.period_s)
        self.io = CyclicIO(self.master_buses, self.cfg.bus, **kw)
        return self.io

    def close(self) -> None:
        self.master.detach()
        self.sim.stop()
        for b in self.sim_buses + self.master_buses:
            b.shutdown()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
