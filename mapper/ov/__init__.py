"""Open-vocabulary embedding spaces: text encoders, the dense CLIP backend and its tokenizer.
"""
