//! Pictures: depth with patches drawn (coloured by validation result) and saliency masks.
