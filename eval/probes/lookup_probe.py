#!/usr/bin/env python3
"""An independent PyTorch replica of the tabletop VLM's look-up problem (eval/journal/2026-11-23.md,
"Why look-up questions stay at chance: layout and relevance probes"; its runs: "The same plateau in an
independent PyTorch replica"), to tell a bug in the Rust training from an optimisation problem. Run
by hand (CI needs no Python): `pip install torch`, then e.g.

    python3 eval/probes/lookup_probe.py steps=1500                      # images first, 8x8 tokens
    python3 eval/probes/lookup_probe.py steps=1000 grid=4 sup=1         # 4x4, supervised attention
    python3 eval/probes/lookup_probe.py steps=600 text_first=1 wordimg=1 tiedqk=1

The LLM follows `train::vlm`'s recipe (Qwen2 blocks: RMSNorm, RoPE, 4 query / 2 KV heads, SwiGLU,
width 128, 4 layers, tied embeddings, N(0, 0.02) init with the output maps scaled by the depth;
AdamW, lr 2e-3, 100 warm-up steps, cosine decay, weight decay 0.01). Images are symbolic: a grid of
tokens, each the sum of fixed random colour / shape / size class vectors and x/y directions, through
a linear-GELU-linear projector (`wordimg=1`: the LLM's own colour and shape word embeddings plus a
learned position vector instead), a newline token after each row. Each step: 16 scenes of 1-6
objects (rectangles of 1-3 patches), 6 questions each (`kinds=exists,count,color_of`), loss on the
answer token; `sup=1` adds a loss on layer `sup_layer`'s heads 0/1 at the answer position: put the
attention on the tokens of the colour / shape the question names. Prints the training loss and the
held-out loss and accuracy every `eval_every` steps.

Further knobs: `init_std` (all matrices, default 0.02), `qk_std` (query/key maps only), `out_scale=0`
(no 1/sqrt(2L) on the output maps), `maxobj` (objects per scene), and with `text_first=1`
`minimal=1` (a row is only the image tokens and the two attribute words; the answer is read at
the last word) or `minimal=2` (the image tokens, then the whole question, answer read at `?`):

    python3 eval/probes/lookup_probe.py steps=1000 grid=4 text_first=1 wordimg=1 minimal=1 lr=0.001
"""
import torch, torch.nn as nn, torch.nn.functional as F, math, random, sys, time, json
torch.set_num_threads(1)
A = dict(steps=600, lr=2e-3, emb_std=0.02, proj_l2=None, img_scale=1.0, layout='images_first', D=128, L=4, H=4, KV=2,
         grid=8, nq=6, nimg=16, seed=0, warm=100, kinds='exists', normimg=False, eval_every=100, sup=0.0, sup_layer=2, text_first=0, wordimg=0, tiedqk=0, init_std=0.02, qk_std=0.0, maxobj=6, out_scale=1, minimal=0)
for a in sys.argv[1:]:
    k, v = a.split('='); A[k] = type(A[k])(v) if A[k] is not None and not isinstance(A[k], bool) else (v=='1' if isinstance(A[k], bool) else float(v))
torch.manual_seed(A['seed']); random.seed(A['seed'])
NC, NS, NZ = 8, 6, 2
words = ['<pad>','<im_start>','<im_end>','<image>','<nl>','user','assistant','is','there','a','?','yes','no','what','color','the','shape','how','many','objects'] + [f'c{i}' for i in range(NC)] + [f's{i}' for i in range(NS)] + [str(i) for i in range(10)]
W = {w:i for i,w in enumerate(words)}
D, G = A['D'], A['grid']
DV = 128
g = torch.Generator().manual_seed(123)
Ccls = torch.randn(NC+1, DV, generator=g); Scls = torch.randn(NS+1, DV, generator=g); Zcls = torch.randn(NZ+1, DV, generator=g)
XY = torch.randn(2, DV, generator=g)
def scene():
    n = random.randint(1, A['maxobj']); occ = torch.zeros(G, G, dtype=torch.long); objs = []
    for _ in range(50):
        if len(objs) == n: break
        z = random.randint(0, 1); w = h = 1 + z + random.randint(0, 1)
        x, y = random.randint(0, G-w), random.randint(0, G-h)
        if occ[y:y+h, x:x+w].any(): continue
        c, s = random.randrange(NC), random.randrange(NS)
        if any(o[0]==c and o[1]==s for o in objs): continue
        objs.append((c, s, z)); occ[y:y+h, x:x+w] = len(objs)
    return objs, occ
def tokens(objs, occ):
    cl = torch.zeros(G*G, dtype=torch.long); sl = cl.clone(); zl = cl.clone()
    for i, (c, s, z) in enumerate(objs):
        m = (occ.flatten() == i+1); cl[m] = c+1; sl[m] = s+1; zl[m] = z+1
    ys, xs = torch.meshgrid(torch.arange(G), torch.arange(G), indexing='ij')
    at = lambda t: ((t.float()+0.5)/G*2-1).flatten()[:, None]
    return Ccls[cl] + Scls[sl] + Zcls[zl] + at(xs)*XY[0] + at(ys)*XY[1]
def questions(objs):
    qs = []
    kinds = A['kinds'].split(',')
    for _ in range(A['nq']):
        k = random.choice(kinds)
        if k == 'exists':
            if random.random() < 0.5:
                c, s, _ = random.choice(objs); a = 'yes'
            else:
                while True:
                    c, s = random.randrange(NC), random.randrange(NS)
                    if not any(o[0]==c and o[1]==s for o in objs): break
                a = 'no'
            qs.append((['is','there','a',f'c{c}',f's{s}','?'], a))
        elif k == 'count':
            qs.append((['how','many','objects','?'], str(len(objs))))
        elif k == 'color_of':
            shapes = [o[1] for o in objs]
            uniq = [o for o in objs if shapes.count(o[1]) == 1]
            if not uniq: continue
            c, s, _ = random.choice(uniq)
            qs.append((['what','color','is','the',f's{s}','?'], f'c{c}'))
    return qs
def rms(d): return nn.RMSNorm(d, eps=1e-6)
def rope(x, pos):
    hd = x.shape[-1]; inv = 1.0 / (10000 ** (torch.arange(0, hd, 2).float() / hd))
    f = pos[:, None].float() * inv[None]; cos, sin = f.cos().repeat(1, 2), f.sin().repeat(1, 2)
    x1, x2 = x[..., :hd//2], x[..., hd//2:]
    return x * cos + torch.cat([-x2, x1], -1) * sin
class Layer(nn.Module):
    def __init__(s):
        super().__init__(); hd = D // A['H']; s.hd = hd
        s.ln1, s.ln2 = rms(D), rms(D)
        s.q = nn.Linear(D, A['H']*hd); s.k = nn.Linear(D, A['KV']*hd); s.v = nn.Linear(D, A['KV']*hd); s.o = nn.Linear(A['H']*hd, D, bias=False)
        s.gate = nn.Linear(D, 3*D, bias=False); s.up = nn.Linear(D, 3*D, bias=False); s.down = nn.Linear(3*D, D, bias=False)
class M(nn.Module):
    def __init__(s):
        super().__init__()
        s.emb = nn.Embedding(len(words), D); s.layers = nn.ModuleList([Layer() for _ in range(A['L'])]); s.norm = rms(D)
        s.p1 = nn.Linear(DV, D); s.p2 = nn.Linear(D, D); s.nl = nn.Parameter(torch.randn(D)*0.02); s.bgv = nn.Parameter(torch.randn(D)*A['emb_std']); s.posv = nn.Parameter(torch.randn(G*G, D)*A['emb_std']*0.3)
        for n, p in s.named_parameters():
            if p.dim() == 2: nn.init.normal_(p, 0, A['init_std'] / (math.sqrt(2*A['L']) if (A['out_scale'] and ('o.' in n or 'down' in n)) else 1))
            if p.dim() == 2 and A['qk_std'] > 0 and (n.endswith('q.weight') or n.endswith('k.weight')): nn.init.normal_(p, 0, A['qk_std'])
            elif n.endswith('bias'): nn.init.zeros_(p)
        nn.init.normal_(s.emb.weight, 0, A['emb_std'])
        if A['tiedqk']:
            for l in s.layers: l.k.weight.data[:] = l.q.weight.data.view(A['KV'], A['H']//A['KV'], -1, D)[:, 0].reshape(-1, D)
        nn.init.normal_(s.p1.weight, 0, 1/math.sqrt(DV)); nn.init.normal_(s.p2.weight, 0, A['proj_l2'] or 1/math.sqrt(D))
    def img(s, t):
        y = s.p2(F.gelu(s.p1(t))) * A['img_scale']
        return y
def build(m, batch):
    # images first: one row per image: prefix + image + all questions as segments (each sees prefix + itself)
    rows = []
    for objs, occ, qs in batch:
        if A['wordimg']:
            cl0 = torch.zeros(G*G, dtype=torch.long); sl0 = cl0.clone()
            for oi, (c_, s_, z_) in enumerate(objs):
                mm_ = (occ.flatten() == oi+1); cl0[mm_] = W[f'c{c_}']; sl0[mm_] = W[f's{s_}']
            bg = (cl0 == 0)
            im = (m.emb(cl0) + m.emb(sl0)) * (~bg)[:, None] + m.bgv * bg[:, None] + m.posv
        else:
            im = m.img(tokens(objs, occ))  # [G*G, D]
        cl = torch.zeros(G*G, dtype=torch.long) - 1; sl = cl.clone()
        for oi, (c_, s_, z_) in enumerate(objs):
            mm_ = (occ.flatten() == oi+1); cl[mm_] = c_; sl[mm_] = s_
        cl = torch.cat([cl.view(G, G), torch.full((G, 1), -1)], 1).flatten(); sl = torch.cat([sl.view(G, G), torch.full((G, 1), -1)], 1).flatten()
        im = torch.cat([im.view(G, G, D), m.nl.view(1, 1, D).expand(G, 1, D)], 1).view(-1, D)
        head = [W['<im_start>'], W['user'], W['<nl>']]
        seq_emb = [m.emb(torch.tensor(head)), im]
        pre = len(head) + im.shape[0]
        segs = []; pos = list(range(pre)); tgt = []; seg_id = [0]*pre
        for j, (qw, a) in enumerate(qs):
            ids = [W[w] for w in qw] + [W['<im_end>'], W['<nl>'], W['<im_start>'], W['assistant'], W['<nl>'], W[a]]
            start = len(pos)
            seq_emb.append(m.emb(torch.tensor(ids)))
            pos += list(range(pre, pre + len(ids))); seg_id += [j+1]*len(ids)
            qc = [int(w[1:]) for w in qw if w.startswith('c')]; qs_ = [int(w[1:]) for w in qw if w.startswith('s')]
            tc = (torch.nonzero(cl == qc[0]).flatten() + len(head)).tolist() if qc else []
            ts = (torch.nonzero(sl == qs_[0]).flatten() + len(head)).tolist() if qs_ else []
            tgt.append((start + len(ids) - 2, W[a], a, tc, ts))
        if not A['text_first']:
            rows.append((torch.cat(seq_emb), pos, seg_id, tgt)); continue
        for (qw, a) in qs:
            if A['minimal']:
                imm = im.view(G, G+1, D)[:, :G].reshape(-1, D)
                qq = qw[3:5] if A['minimal'] == 1 else qw
                e = torch.cat([imm, m.emb(torch.tensor([W[w] for w in qq]))]); n = e.shape[0]
                rows.append((e, list(range(n)), [0]*n, [(n - 1, W[a], a, [], [])])); continue
            qids = [W[w] for w in qw]
            tail = [W['<im_end>'], W['<nl>'], W['<im_start>'], W['assistant'], W['<nl>'], W[a]]
            e = torch.cat([m.emb(torch.tensor(head + qids)), im, m.emb(torch.tensor(tail))])
            n = e.shape[0]; off = len(head) + len(qids)
            qc = [int(w[1:]) for w in qw if w.startswith('c')]; qs_ = [int(w[1:]) for w in qw if w.startswith('s')]
            tc = (torch.nonzero(cl == qc[0]).flatten() + off).tolist() if qc else []
            ts = (torch.nonzero(sl == qs_[0]).flatten() + off).tolist() if qs_ else []
            rows.append((e, list(range(n)), [0]*n, [(n - 2, W[a], a, tc, ts)]))
    T = max(r[0].shape[0] for r in rows)
    x = torch.zeros(len(rows), T, D); P = torch.zeros(len(rows), T, dtype=torch.long); mask = torch.full((len(rows), 1, T, T), float('-inf'))
    for b, (e, pos, sid, _) in enumerate(rows):
        n = e.shape[0]; x[b, :n] = e; P[b, :n] = torch.tensor(pos)
        sid = torch.tensor(sid); i = torch.arange(n)
        ok = (i[None] <= i[:, None]) & ((sid[None] == 0) | (sid[None] == sid[:, None]))
        mm = torch.where(ok, 0.0, float('-inf')); mask[b, 0, :n, :n] = mm
        mask[b, 0, n:, :] = 0.0
    return x, P, mask, [r[3] for r in rows]
def run(m, batch):
    x, P, mask, tg = build(m, batch)
    sup = torch.zeros(())
    for li, l in enumerate(m.layers):
        x, att = layer_batched(l, x, P, mask)
        if li == A['sup_layer'] and A['sup'] > 0:
            terms = []
            for b, tt in enumerate(tg):
                for (t, w, a, tc, ts) in tt:
                    for h, tgt_ in ((0, tc), (1, ts)):
                        if tgt_: terms.append(-torch.log(att[b, h, t, tgt_].sum() + 1e-6))
            if terms: sup = torch.stack(terms).mean()
    x = m.norm(x); logits = x @ m.emb.weight.T
    idx = [(b, t, w) for b, tt in enumerate(tg) for (t, w, a, *_) in tt]
    lg = logits[[i[0] for i in idx], [i[1] for i in idx]]
    y = torch.tensor([i[2] for i in idx])
    return F.cross_entropy(lg, y), (lg.argmax(-1) == y).float().mean().item(), sup
def layer_batched(l, x, P, mask):
    B, T, _ = x.shape; h = l.ln1(x)
    q = l.q(h).view(B, T, A['H'], l.hd).transpose(1, 2); k = l.k(h).view(B, T, A['KV'], l.hd).transpose(1, 2); v = l.v(h).view(B, T, A['KV'], l.hd).transpose(1, 2)
    q = torch.stack([rope(q[b], P[b]) for b in range(B)]); k = torch.stack([rope(k[b], P[b]) for b in range(B)])
    r = A['H'] // A['KV']; k, v = k.repeat_interleave(r, 1), v.repeat_interleave(r, 1)
    att = torch.softmax(q @ k.transpose(-1, -2) / math.sqrt(l.hd) + mask, -1)
    a = att @ v
    x = x + l.o(a.transpose(1, 2).reshape(B, T, -1)); h = l.ln2(x)
    return x + l.down(F.silu(l.gate(h)) * l.up(h)), att
m = M()
opt = torch.optim.AdamW(m.parameters(), lr=A['lr'], weight_decay=0.01)
def lr_at(i):
    if i < A['warm']: return A['lr'] * (i+1) / A['warm']
    t = (i - A['warm']) / max(1, A['steps'] - A['warm']); return 1e-4 + 0.5*(A['lr']-1e-4)*(1+math.cos(math.pi*t))
def mk(n):
    out = []
    while len(out) < n:
        objs, occ = scene(); qs = questions(objs)
        if qs: out.append((objs, occ, qs))
    return out
random.seed(999); held = mk(64); random.seed(A['seed'])
t0 = time.time(); hist = []; sh = []
for i in range(A['steps']):
    for gp in opt.param_groups: gp['lr'] = lr_at(i)
    loss, acc, sup = run(m, mk(A['nimg']))
    opt.zero_grad(); (loss + A['sup'] * sup).backward(); opt.step(); hist.append(loss.item()); sh.append(sup.item())
    if (i+1) % A['eval_every'] == 0:
        with torch.no_grad(): hl, ha, _ = run(m, held)
        print(f"{i+1} {time.time()-t0:.0f}s train {sum(hist[-50:])/50:.3f} sup {sum(sh[-50:])/50:.3f} held loss {hl:.3f} acc {ha:.3f}", flush=True)
