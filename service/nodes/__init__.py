"""Zenoh nodes (emulator, recorder, analyzer, replayer) and the wire contract.

wire/ holds keys, payloads, schemas and time; mcapio.py reads and writes recordings.
"""
