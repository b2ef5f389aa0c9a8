"""The effect zoo: test cases for `hybridize` drawn at random from an integer seed.

    bases.py     the declared models (bundled examples, Modelica Reference FMUs in reference_fmus/)
                 and how their runs are excited
    effects.py   the effect families, evaluated with numpy and written as ONNX
    generate.py  one case per seed: the truth FMU (checked against declared + effect), the
                 measured data, truth.json, and the batch manifest

benchmarks/bench_zoo.py runs hybridize on the cases and scores them; tests/test_zoo.py runs three.
Seeds 1000-1049 are reserved for the reported numbers: develop on seeds below 1000.
"""
