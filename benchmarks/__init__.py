"""msdnet.benchmarks"""
