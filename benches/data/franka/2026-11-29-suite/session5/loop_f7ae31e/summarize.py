import re,glob,sys,os
d=sys.argv[1]
files=sorted(glob.glob(f'{d}/suite_*.txt'),key=lambda f:int(re.findall(r'(\d+)\.txt',f)[0]))
tot={'nj':0,'fh':0}
track=[];led=[];chunks=[];steal=[];notled=[]
for f in files:
    t=open(f).read()
    res=re.findall(r'^test result: (\w+)\. (\d+) passed; (\d+) failed',t,re.M)
    nj=t.count('NOT JUDGED'); tot['nj']+=nj
    fh=sum(int(x) for x in re.findall(r'first_held=(\d+)',t))-t.count('self-test: first_held=1'); tot['fh']+=fh
    for m in re.finditer(r'^(replace|crossfade|temporal_ensemble|rtc|rtc_trained|blend): franka summary.*',t,re.M):
        track.append(float(re.search(r'max_tracking_error=([0-9.]+)',m.group(0)).group(1)))
    for m in re.finditer(r'led_share=([0-9.]+) not_led_longest_ms=(\d+)',t):
        led.append(float(m.group(1))); notled.append(int(m.group(2)))
    c=re.findall(r'(\d+) chunks in ([0-9.]+) s',t); chunks+= [float(x[1]) for x in c]
    steal+=[float(x) for x in re.findall(r'hypervisor took ([0-9.]+) %',t)]
    failed=re.findall(r'^test (\w+) \.\.\. .*?FAILED',t,re.M|re.S)
    fl=[l.split(' ')[1] for l in t.splitlines() if l.startswith('---- ')]
    print(os.path.basename(f),res,'NOT_JUDGED',nj,'first_held',fh,'failed:',fl)
print('strategies max_tracking_error: min %.4f max %.4f n %d'%(min(track),max(track),len(track)) if track else '')
print('random droid: 10 chunks in %.1f-%.1f s'%(min(chunks),max(chunks)) if chunks else '')
print('host steal per test: %.1f-%.1f %%'%(min(steal),max(steal)) if steal else '')
print('NOT JUDGED total',tot['nj'],'first_held total (not the self-test)',tot['fh'])
