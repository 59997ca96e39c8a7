"""Neural against classical on the same scenes: python evaluate.py [suite=quick] [methods=[...]] [scenes=[...]]"""

from neuralsurf.cli import evaluate_main

if __name__ == "__main__":
    evaluate_main()
