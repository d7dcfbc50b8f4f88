"""Zenoh nodes (emulator, recorder, analyzer, replayer).

The wire contract (keys, payloads, schemas, time) is :mod:`noiselab.wire`; recordings are read and
written by :mod:`noiselab.recordings`.
"""
