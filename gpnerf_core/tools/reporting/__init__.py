"""Reading finished run folders back: tables beside the paper's numbers, and accuracy-against-cost charts."""
