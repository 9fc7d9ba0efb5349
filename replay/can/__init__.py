"""CAN: the DBC codec, frames to samples (decode and alignment) and back (encode), CAN log files, a live bus."""
