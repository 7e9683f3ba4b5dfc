"""The tower's shape problem in PyTorch: a ViT of the tabletop tower's size (width 128, 4 layers,
4 heads, patch 12 on 96 px crops) trained on the very crops and per-token labels the Rust trainer
uses (written by `cargo run --release -p eval --example dump_crops -- 8000 /tmp/crops.bin`),
per-token cross-entropy on shape (multi=1: the mean of colour, shape and size, as the Rust
auxiliary loss), AdamW. Prints train / held-out per-token shape accuracy on object tokens every
100 steps. Run by hand (2 threads): python3 eval/probes/tower_probe.py steps=400 multi=1 pos=sincos
Options: key=value for any key of A below; model=cnn for a small conv net instead.
"""
import torch, torch.nn as nn, torch.nn.functional as F, numpy as np, sys, time, math
torch.set_num_threads(2); torch.manual_seed(0)
A = dict(crops='/tmp/crops.bin', pos='rand', multi=0, ln=1e-5, act='gelu', init=0.0, sched=0, model='vit', steps=400, bs=16, lr=1e-3, layers=4, D=128, patch=12)
for a in sys.argv[1:]:
    k, v = a.split('='); A[k] = type(A[k])(v)
S = 96; G = S // 12
raw = np.fromfile(A['crops'], dtype=np.uint8).reshape(-1, 3 * S * S + 64 * 3)
X = torch.tensor(raw[:, :3 * S * S].reshape(-1, 3, S, S)).float() / 255 * 2 - 1
L = torch.tensor(raw[:, 3 * S * S:].reshape(-1, 64, 3)).long()
shape = L[:, :, 1]; obj = L[:, :, 0] > 0
print(X.shape, (shape[obj] > 0).float().mean())
class ViT(nn.Module):
    def __init__(s):
        super().__init__(); D = A['D']; p = A['patch']
        s.pe = nn.Conv2d(3, D, p, p); n = (S // p) ** 2
        s.pos = nn.Parameter(torch.randn(n, D) * 0.02)
        if A['pos'] == 'sincos':
            g = int(n ** 0.5); q = D // 4; om = 1.0 / 10000 ** (torch.arange(q) / q)
            ys, xs = torch.meshgrid(torch.arange(g).float(), torch.arange(g).float(), indexing='ij')
            ex = xs.reshape(-1, 1) * om; ey = ys.reshape(-1, 1) * om
            s.pos = nn.Parameter(torch.cat([ex.sin(), ex.cos(), ey.sin(), ey.cos()], 1))
        s.enc = nn.TransformerEncoder(nn.TransformerEncoderLayer(D, 4, 3 * D, 0.0, activation=(lambda x: F.gelu(x, approximate='tanh')) if A['act'] == 'tanh' else 'gelu', batch_first=True, norm_first=True, layer_norm_eps=A['ln']), A['layers'])
        s.head = nn.Linear(D, 7 + 9 + 3)
    def forward(s, x):
        t = s.pe(x).flatten(2).transpose(1, 2) + s.pos
        t = s.enc(t)
        if A['patch'] != 12:  # pool back to 8x8 for labels
            g = S // A['patch']; t = t.transpose(1, 2).reshape(-1, A['D'], g, g); t = F.adaptive_avg_pool2d(t, 8).flatten(2).transpose(1, 2)
        return s.head(t)
class CNN(nn.Module):
    def __init__(s):
        super().__init__(); D = A['D']
        s.net = nn.Sequential(nn.Conv2d(3, 32, 3, 2, 1), nn.GELU(), nn.Conv2d(32, 64, 3, 2, 1), nn.GELU(), nn.Conv2d(64, D, 3, 3, 0), nn.GELU(), nn.Conv2d(D, D, 3, 1, 1), nn.GELU(), nn.Conv2d(D, D, 3, 1, 1))
        s.head = nn.Linear(D, 7)
    def forward(s, x):
        t = s.net(x)  # [B, D, 8, 8]
        return s.head(t.flatten(2).transpose(1, 2))
m = ViT() if A['model'] == 'vit' else CNN()
if A['init'] > 0:
    for n, p in m.named_parameters():
        if p.dim() == 2 and 'pos' not in n: nn.init.normal_(p, 0, A['init'])
opt = torch.optim.AdamW(m.parameters(), lr=A['lr'])
t0 = time.time(); accs = []
for i in range(A['steps']):
    idx = torch.randint(0, 7000, (A['bs'],))
    if A['sched']:
        for gp in opt.param_groups: gp['lr'] = A['lr'] * min(1, (i + 1) / 50) * (0.1 + 0.45 * (1 + math.cos(math.pi * i / A['steps'])))
    out = m(X[idx]); lg = out[..., :7]; y = shape[idx]
    loss = F.cross_entropy(lg.reshape(-1, 7), y.reshape(-1))
    if A['multi']:
        col = L[idx][:, :, 0]; siz = L[idx][:, :, 2]
        loss = (loss + F.cross_entropy(out[..., 7:16].reshape(-1, 9), col.reshape(-1)) + F.cross_entropy(out[..., 16:].reshape(-1, 3), siz.reshape(-1))) / 3
    opt.zero_grad(); loss.backward(); opt.step()
    o = obj[idx]; accs.append(((lg.argmax(-1) == y)[o]).float().mean().item())
    if (i + 1) % 100 == 0:
        with torch.no_grad():
            lg = m(X[7000:7500])[..., :7]; o = obj[7000:7500]
            ha = ((lg.argmax(-1) == shape[7000:7500])[o]).float().mean().item()
        print(i + 1, f"{time.time() - t0:.0f}s train {np.mean(accs[-50:]):.2f} held {ha:.2f}", flush=True)
