#!/usr/bin/env python3
"""Text-only look-up, the control for `lookup_probe.py` (eval/journal/2026-11-23.md, "What moves
the look-up plateau: a text-only control, learning rate and layout"). Run by hand (CI needs no
Python). A row lists 1-6 objects as words (colour, shape), then `? <colour> <shape>`; the answer
(yes/no: is that object in the list) is read at the last word. Same widths as the tabletop LLM
(128 x 4 layers), AdamW, batch 128 fresh rows, 100 warm-up steps; prints the held-out accuracy
(1,000 rows) every `ev` steps.

    python3 eval/probes/text_lookup_probe.py                       # GPT blocks, two words per object
    python3 eval/probes/text_lookup_probe.py fused=1 qwen=1        # one token per object, Qwen2 blocks
    python3 eval/probes/text_lookup_probe.py fused=1 bg=20         # + 20 empty tokens among the objects

`fused=1`: an object is one token, the sum of its colour and shape embeddings (as an image token
carries both); `bg=K`: K empty tokens placed at random among the objects; `mask_bg_until=S`: the
empty tokens are hidden from attention for the first S steps; `qwen=1`: Qwen2 blocks (RMSNorm,
RoPE, 4 query / 2 KV heads, SwiGLU, tied embeddings, output maps scaled by 1/sqrt(2L)).
"""
import torch, torch.nn as nn, torch.nn.functional as F, random, sys, time, math
torch.set_num_threads(1)
A=dict(steps=3000,lr=1e-3,D=128,L=4,B=128,maxobj=6,init=0.02,nc=8,ns=6,seed=0,ev=100,fused=0,bg=0,mask_bg_until=0,qwen=0,tied=1,absp=0,dscale=1)
for a in sys.argv[1:]:
    k,v=a.split('='); A[k]=type(A[k])(v)
torch.manual_seed(A['seed']); random.seed(A['seed'])
NC,NS=A['nc'],A['ns']; V=NC+NS+4  # pad ? yes no
Q,YES,NO,PAD=NC+NS,NC+NS+1,NC+NS+2,NC+NS+3
def sample():
    n=random.randint(1,A['maxobj']); objs=set()
    while len(objs)<n: objs.add((random.randrange(NC),random.randrange(NS)))
    objs=list(objs); random.shuffle(objs)
    if random.random()<0.5: c,s=random.choice(objs); a=YES
    else:
        while True:
            c,s=random.randrange(NC),random.randrange(NS)
            if (c,s) not in objs: break
        a=NO
    seq=[]
    for (oc,os) in objs: seq+=[oc,NC+os]
    seq+=[PAD]*(2*A['maxobj']-len(seq))
    if A['fused']: seq=seq[0::2]+seq[1::2]
    if A['bg']:
        k=A['maxobj']; cells=[PAD]*(k+A['bg']); idx=sorted(random.sample(range(k+A['bg']),k))
        cc=[PAD]*(k+A['bg']); ss=[PAD]*(k+A['bg'])
        for j,i in enumerate(idx): cc[i]=seq[j]; ss[i]=seq[k+j]
        seq=cc+ss+seq[2*k:]
    seq+=[Q,c,NC+s]
    return seq,a
T=2*A['maxobj']+3
class Blk(nn.Module):
    def __init__(s,D):
        super().__init__(); s.l1=nn.LayerNorm(D); s.att=nn.MultiheadAttention(D,4,batch_first=True); s.l2=nn.LayerNorm(D); s.mlp=nn.Sequential(nn.Linear(D,4*D),nn.GELU(),nn.Linear(4*D,D))
    def forward(s,x,m):
        h=s.l1(x); x=x+s.att(h,h,h,attn_mask=m,need_weights=False)[0]; return x+s.mlp(s.l2(x))
def rope(x):
    T_=x.shape[-2]; hd=x.shape[-1]; inv=1.0/(10000**(torch.arange(0,hd,2).float()/hd))
    f=torch.arange(T_)[:,None].float()*inv[None]; cos,sin=f.cos().repeat(1,2),f.sin().repeat(1,2)
    x1,x2=x[...,:hd//2],x[...,hd//2:]; return x*cos+torch.cat([-x2,x1],-1)*sin
class QB(nn.Module):
    def __init__(s,D,H=4,KV=2):
        super().__init__(); s.H,s.KV,s.hd=H,KV,D//H; s.l1=nn.RMSNorm(D,eps=1e-6); s.l2=nn.RMSNorm(D,eps=1e-6)
        s.q=nn.Linear(D,H*s.hd); s.k=nn.Linear(D,KV*s.hd); s.v=nn.Linear(D,KV*s.hd); s.o=nn.Linear(H*s.hd,D,bias=False)
        s.gate=nn.Linear(D,3*D,bias=False); s.up=nn.Linear(D,3*D,bias=False); s.down=nn.Linear(3*D,D,bias=False)
    def forward(s,x,m):
        B,T_,_=x.shape; h=s.l1(x)
        q=rope(s.q(h).view(B,T_,s.H,s.hd).transpose(1,2)); k=rope(s.k(h).view(B,T_,s.KV,s.hd).transpose(1,2)); v=s.v(h).view(B,T_,s.KV,s.hd).transpose(1,2)
        r=s.H//s.KV; k,v=k.repeat_interleave(r,1),v.repeat_interleave(r,1)
        mm=m if m.dim()==2 else m.view(B,4,T_,T_)
        a=torch.softmax(q@k.transpose(-1,-2)/math.sqrt(s.hd)+mm,-1)@v
        x=x+s.o(a.transpose(1,2).reshape(B,T_,-1)); h=s.l2(x)
        return x+s.down(F.silu(s.gate(h))*s.up(h))
class M(nn.Module):
    def __init__(s):
        super().__init__(); D=A['D']; s.e=nn.Embedding(V,D); s.p=nn.Parameter(torch.randn(T+2*A['bg'],D)*A['init']); s.b=nn.ModuleList([(QB(D) if A['qwen'] else Blk(D)) for _ in range(A['L'])]); s.n=nn.RMSNorm(D,eps=1e-6) if A['qwen'] else nn.LayerNorm(D); s.o=nn.Linear(D,V)
        for n_,p in s.named_parameters():
            if p.dim()==2: nn.init.normal_(p,0,A['init']/(math.sqrt(2*A['L']) if (A['dscale'] and ('.o.' in n_ or 'down' in n_)) else 1))
            if n_.endswith('bias'): nn.init.zeros_(p)
    def forward(s,x,hide=False):
        TT=(A['maxobj']+A['bg']+3) if A['fused'] else T; m=torch.triu(torch.full((TT,TT),float('-inf')),1)
        if A['fused']:
            k=A['maxobj']+A['bg']; o=s.e(x[:,:k])+s.e(x[:,k:2*k]); h=torch.cat([o,s.e(x[:,2*k:])],1)+(s.p[:k+3] if (A['absp'] or not A['qwen']) else 0)
        else: h=s.e(x)+s.p
        if hide:
            k=A['maxobj']+A['bg']; keyhide=torch.zeros(x.shape[0],TT,dtype=torch.bool); keyhide[:,:k]=(x[:,:k]==PAD)
            m=m[None].expand(x.shape[0],TT,TT).clone(); m[keyhide[:,None,:].expand(-1,TT,-1)]=float('-inf')
            eye=torch.eye(TT,dtype=torch.bool)[None].expand(x.shape[0],-1,-1); m[eye]=0.0
            m=m.repeat_interleave(4,0)
        for b in s.b: h=b(h,m)
        hl=s.n(h[:,-1]); return hl@s.e.weight.T if (A['qwen'] and A['tied']) else s.o(hl)
m=M(); opt=torch.optim.AdamW(m.parameters(),lr=A['lr'],weight_decay=0.01)
random.seed(999); held=[sample() for _ in range(1000)]; random.seed(A['seed'])
hx=torch.tensor([h[0] for h in held]); hy=torch.tensor([h[1] for h in held])
t0=time.time()
for i in range(A['steps']):
    bt=[sample() for _ in range(A['B'])]; x=torch.tensor([b[0] for b in bt]); y=torch.tensor([b[1] for b in bt])
    for g in opt.param_groups: g['lr']=A['lr']*min(1,(i+1)/100)
    loss=F.cross_entropy(m(x,hide=i<A['mask_bg_until']),y); opt.zero_grad(); loss.backward(); opt.step()
    if (i+1)%A['ev']==0:
        with torch.no_grad(): acc=(m(hx).argmax(-1)==hy).float().mean().item()
        print(i+1,'hidden' if i<A['mask_bg_until'] else 'all',f"{time.time()-t0:.0f}s loss {loss.item():.3f} held {acc:.3f}",flush=True)
