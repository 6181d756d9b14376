"""What a forward will cost before it runs: FLOPs from the static plans (`cost`) and
XLA's memory plan of the compiled program (`memory`), also for a GPU or TPU that is not
here (`targets`: XLA's own compilers for named accelerators, without the device); and how
long it will take on this CPU (`estimate`: those FLOPs at a rate measured here).
"""
