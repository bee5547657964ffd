"""hexacnc: real-time soft-CNC transformation daemon for hexapod machine tools."""
__version__ = "0.1.0"
