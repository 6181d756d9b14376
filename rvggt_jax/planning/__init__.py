"""What a forward will cost before it runs: FLOPs from the static plans (`cost`) and
XLA's memory plan of the compiled program (`memory`).
"""
