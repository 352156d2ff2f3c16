"""msdnet.training"""
