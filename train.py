"""Fit a neural surface: python train.py experiment=bunny_sdf [key=value ...]"""

from neuralsurf.cli import train_main

if __name__ == "__main__":
    train_main()
