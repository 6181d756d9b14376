"""Operations the model is built from: the one attention op and its kernels, the chunk
loops over tokens, the exchanges between devices holding frames, and the XLA:CPU setting.
"""
