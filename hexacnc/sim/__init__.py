"""The machine simulator: thermal drift and its compensation, strut and carrier dynamics,
controller structures (``hexacnc simulate thermal|dynamics|controller``).

Modules: :mod:`.program` (test programs and their strut commands), :mod:`.thermal`
(end-to-end thermal drift), :mod:`.dynamics` (equations 3-5: coupled strut/carrier
model, eigen-analysis, path simulation), :mod:`.controller` (cascade vs coupled
state controller), :mod:`.strut` (strut dynamics model for simulated drives).
"""
