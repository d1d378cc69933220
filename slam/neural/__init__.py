"""The neural allocentric spatial memory of thesis chapter 4 (MapNet-style localisation, LSTM memory,
recall by geometric culling + decoding, hallucination of unseen regions), in PyTorch."""
